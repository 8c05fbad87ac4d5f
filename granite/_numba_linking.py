"""Keep the LLVM IR of kernels loaded from numba's cache as bitcode until it is needed.

For every kernel numba loads from its on-disk cache it also parses the kernel's LLVM bitcode
(the kernel and all its callees) into an in-memory LLVM module and keeps it for the life of
the process (``CPUCodeLibrary._shared_module``). That module has one use: linking the kernel
into another kernel compiled later in the same process (a caller whose own cache entry is
missing). The machine code that runs comes from the cached object code. For the VO's kernels
the parsed modules take about 54 MB of resident memory (of ~300 MB for a whole run; the
bitcode itself is ~10 MB), measured by dropping them after a 640x480 run
(``benchmarks/bench_memory.py`` prints the stages).

:func:`install` patches numba's ``CPUCodeLibrary`` so that a library loaded from the cache keeps
the bitcode bytes instead, and parses them again the first time it is linked into another
kernel (``_get_module_for_linking``): what numba links, and when, is unchanged. Only numba's
private ``_unserialize`` / ``_get_module_for_linking`` are touched; when they do not look as
expected (another numba than ``pyproject.toml`` pins) nothing is patched and numba behaves as
shipped. :func:`install_when_numba_loads` (run by ``import granite``) applies the patch when
numba is imported, so that importing granite does not import numba.
"""

from __future__ import annotations

import importlib.abc
import sys

_PATCHED_MODULE = "numba.core.codegen"
_MARK = "_granite_lazy_linking_ir"
_BITCODE = "_granite_linking_bitcode"


def install() -> bool:
    """Patch numba (imported by this call) so cache-loaded kernels keep bitcode, not parsed
    IR; returns whether numba is patched (False when its internals are not the expected ones)."""
    from llvmlite import binding as llvm
    from numba.core import codegen

    cls = codegen.CPUCodeLibrary
    if getattr(cls, _MARK, False):
        return True
    unserialize = cls.__dict__.get("_unserialize")
    module_for_linking = cls.__dict__.get("_get_module_for_linking")
    if not isinstance(unserialize, classmethod) or not callable(module_for_linking):
        return False
    load_library = unserialize.__func__

    def _unserialize(klass, codegen_, state):
        library = load_library(klass, codegen_, state)
        kind, data = state[1], state[2]
        if kind == "object" and getattr(library, "_shared_module", None) is not None:
            setattr(library, _BITCODE, data[1])  # the bytes numba parsed: no copy
            library._shared_module = None
        return library

    def _get_module_for_linking(self):
        bitcode = self.__dict__.pop(_BITCODE, None)
        if bitcode is not None and self._shared_module is None:
            self._shared_module = llvm.parse_bitcode(bitcode)
        return module_for_linking(self)

    cls._unserialize = classmethod(_unserialize)
    cls._get_module_for_linking = _get_module_for_linking
    setattr(cls, _MARK, True)
    return True


class _PatchAfterImport(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds ``numba.core.codegen`` with the normal finders and patches it once executed."""

    def find_spec(self, fullname, path, target=None):
        if fullname != _PATCHED_MODULE:
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(fullname, path, target)
            if spec is not None:
                self._loader = spec.loader
                spec.loader = self
                return spec
        return None

    def create_module(self, spec):
        return self._loader.create_module(spec)

    def exec_module(self, module):
        self._loader.exec_module(module)
        sys.meta_path[:] = [f for f in sys.meta_path if f is not self]
        install()


def install_when_numba_loads() -> None:
    """Apply :func:`install` now if numba's codegen is imported, else right after its import."""
    if _PATCHED_MODULE in sys.modules:
        install()
    elif not any(isinstance(f, _PatchAfterImport) for f in sys.meta_path):
        sys.meta_path.insert(0, _PatchAfterImport())
