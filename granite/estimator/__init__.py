"""The monocular odometry pipeline (paper Fig. 2b), wired around the frontend and the backend.

``vo`` (:class:`~granite.estimator.vo.MonocularVO`, one frame at a time) uses
``tracking_state`` (the state machine), ``map_initialization`` (two-view start of a map, on
``initialization``'s relative-pose solver), ``landmark_creation`` (new and re-triangulated
landmarks), ``keyframes`` (negative-entropy criterion), ``window_policy`` (which frames leave the
window) and ``motion_model`` (constant-velocity guesses). ``runner`` drives a whole dataset and
writes the run folder; ``config`` is the TOML configuration of every component.
"""
