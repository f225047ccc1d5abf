"""A one-line notice on stderr when Warp compiles warpblob's kernels.

Warp compiles a module on its first launch unless its kernel cache already
holds it; for warpblob's evaluators that takes a minute or two on a fresh
machine, and without a terminal (so without progress bars) the process would
look hung. The notice is printed once per process, when the first warpblob
module actually starts compiling: never when every module comes from the
cache, and never for other libraries' (or the user's) Warp modules.

The hook wraps ``Module._run_codegen`` of Warp's runtime, which Warp calls
after its kernel-cache lookup missed and before code generation and the C++
or CUDA compiler run. Warp keeps no public event for that moment: with a Warp
that lacks the method nothing is hooked and there is no notice; the test
suite checks that the hook is in place, so a Warp release that renames the
method fails there.
"""

from __future__ import annotations

import functools
import sys
import threading

import warp as wp

__all__ = ["NOTICE", "install"]

NOTICE = "warpblob: compiling Warp kernels (first use only, about a minute) ..."
_PACKAGE = __name__.split(".")[0]
_lock = threading.Lock()
_shown = False


def _is_ours(module: wp.Module) -> bool:
    """Whether ``module`` holds a kernel defined in warpblob (unique modules are named after the kernel only)."""
    for kernel in list(module.kernels.values()):
        owner = getattr(getattr(kernel, "func", None), "__module__", None) or ""
        if owner == _PACKAGE or owner.startswith(_PACKAGE + "."):
            return True
    return False


def _notify(module: wp.Module) -> None:
    global _shown
    if _shown or not _is_ours(module):
        return
    with _lock:
        # pool threads may start compiling different modules at the same moment
        if _shown:
            return
        _shown = True
    print(NOTICE, file=sys.stderr, flush=True)


def install() -> None:
    """Hook the notice into Warp's compile path (idempotent; a no-op where Warp has no such step)."""
    original = getattr(getattr(wp, "Module", None), "_run_codegen", None)
    if original is None or getattr(original, "_warpblob_notice", False):
        return

    @functools.wraps(original)
    def run_codegen(self, *args, **kwargs):
        _notify(self)
        return original(self, *args, **kwargs)

    run_codegen._warpblob_notice = True
    wp.Module._run_codegen = run_codegen

