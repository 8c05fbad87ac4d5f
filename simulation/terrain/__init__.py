"""Procedural Mars-analogue terrain: numpy model (:mod:`.heightfield`, :mod:`.rocks`,
:mod:`.textures`, :mod:`.appearance`, :mod:`.model`) and its Blender scene (:mod:`.scene`)."""
