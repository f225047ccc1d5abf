"""Range-split launches: coverage of the range, the thread pool's life cycle,
one compilation per module, and the compile notice."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import threading

import numpy as np
import pytest
import warp as wp

import warpblob as wb
from warpblob import _compile, _parallel


@wp.kernel(enable_backward=False)
def count_items_kernel(offset: int, hits: wp.array(dtype=wp.int32)):
    i = wp.tid() + offset
    hits[i] = hits[i] + 1


def _pool_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("warpblob")]


@pytest.mark.parametrize("threads", [1, 2, 3, 7])
@pytest.mark.parametrize("dim", [1, 2047, 2048, 100_003])
def test_launch_covers_every_item_once(threads, dim):
    hits = wp.zeros(dim, dtype=wp.int32, device="cpu")
    _parallel.launch(count_items_kernel, dim, [], [hits], "cpu", threads)
    assert np.all(hits.numpy() == 1)


def test_launch_refuses_bad_threads():
    hits = wp.zeros(4096, dtype=wp.int32, device="cpu")
    for bad in (0, -1, 2.5, True):
        with pytest.raises(wb.WarpblobError, match=f"got {bad!r}"):
            _parallel.launch(count_items_kernel, 4096, [], [hits], "cpu", bad)
    assert np.all(hits.numpy() == 0)


def test_growing_the_pool_does_not_leak_threads():
    _parallel._shutdown()
    assert not _pool_threads()
    hits = wp.zeros(1 << 16, dtype=wp.int32, device="cpu")
    largest = 0
    for n in (2, 4, 3, 8, 5, 16, 12):
        largest = max(largest, n)
        # held here, a replaced pool is not garbage: only shutting it down ends its threads
        previous = _parallel._pool
        _parallel.launch(count_items_kernel, hits.shape[0], [], [hits], "cpu", n, min_chunk=64)
        assert len(_pool_threads()) <= largest
        del previous
    assert np.all(hits.numpy() == 7)
    _parallel._shutdown()
    assert not _pool_threads()
    # a launch after the shutdown starts a fresh pool
    _parallel.launch(count_items_kernel, hits.shape[0], [], [hits], "cpu", 2, min_chunk=64)
    assert np.all(hits.numpy() == 8)


def test_concurrent_callers_while_the_pool_grows():
    model = wb.scenes.tumor()
    pts = np.random.default_rng(1).uniform(-1.5, 1.5, (20_000, 3)).astype(np.float32)
    expect = wb.evaluate(model, pts, threads=1)
    _parallel._shutdown()
    errors, results = [], []

    def caller(k):
        try:
            for n in (1 + k % 3, 2 + k, 3 + 2 * k):  # callers grow the pool under each other
                results.append(wb.evaluate(model, pts, threads=n))
        except Exception as exc:  # noqa: BLE001 (reported below)
            errors.append(exc)

    callers = [threading.Thread(target=caller, args=(k,)) for k in range(5)]
    for t in callers:
        t.start()
    for t in callers:
        t.join()
    assert not errors
    assert len(results) == 15
    for got in results:
        for a, b in zip(got, expect):
            assert a.tobytes() == b.tobytes()
    assert len(_pool_threads()) <= 11  # the largest pool asked for


def test_a_module_compiles_once_whatever_the_thread_count(tmp_path, monkeypatch):
    """Every pool thread's first launch would compile the module at the same
    time; :func:`launch` loads it once before handing out the pieces."""

    @wp.kernel(enable_backward=False, module="unique")
    def compile_once_probe_kernel(offset: int, out: wp.array(dtype=wp.float32)):
        i = wp.tid() + offset
        out[i] = wp.sqrt(float(i))

    compiled = []
    original = wp.Module._run_codegen

    def counting(self, *args, **kwargs):
        compiled.append(self.name)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))  # empty: nothing is cached
    monkeypatch.setattr(wp.Module, "_run_codegen", counting)
    out = wp.zeros(1 << 14, dtype=wp.float32, device="cpu")
    _parallel.launch(compile_once_probe_kernel, out.shape[0], [], [out], "cpu", 4, min_chunk=16)
    assert compiled == [compile_once_probe_kernel.module.name]
    np.testing.assert_allclose(out.numpy(), np.sqrt(np.arange(out.shape[0], dtype=np.float32)), rtol=1e-6)


_NOTICE_SCRIPT = textwrap.dedent(
    """
    import sys
    import numpy as np
    import warp as wp
    import warpblob as wb
    from warpblob.field import bound_balls

    @wp.kernel
    def user_kernel(a: wp.array(dtype=float)):
        a[wp.tid()] = 1.0

    wp.launch(user_kernel, dim=1, inputs=[wp.zeros(1, device="cpu")], device="cpu")
    print("user kernel done", file=sys.stderr, flush=True)
    model = wb.Point((0, 0, 0), 1.0)
    # the input checks' kernels are warpblob's smallest; the NaN stops each call before the evaluator compiles
    for call in (
        lambda: wb.field(model, wp.array(np.array([[0, 0, np.nan]], np.float32), dtype=wp.vec3, device="cpu")),
        lambda: bound_balls(model, np.zeros((1, 3)), wp.array(np.array([np.nan], np.float32), device="cpu")),
    ):
        try:
            call()
        except wb.ModelError:
            pass
    """
)


def _run_notice_script(tmp_path, cache: str, **env) -> str:
    script = tmp_path / "notice.py"  # Warp reads kernel source from files, not from -c
    script.write_text(_NOTICE_SCRIPT)
    environ = {k: v for k, v in os.environ.items() if k != "WARPBLOB_VERBOSE"}
    environ.update(WARP_CACHE_PATH=str(tmp_path / cache), **env)
    done = subprocess.run([sys.executable, str(script)], env=environ, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return done.stderr


def test_compile_notice_once_and_only_when_compiling(tmp_path):
    assert getattr(wp.Module._run_codegen, "_warpblob_notice", False), "the notice's hook into Warp is missing"
    cold = _run_notice_script(tmp_path, "cache")
    assert cold.count(_compile.NOTICE) == 1
    # the user's own kernel compiled first, without the notice
    assert cold.index("user kernel done") < cold.index(_compile.NOTICE)
    warm = _run_notice_script(tmp_path, "cache")
    assert _compile.NOTICE not in warm
    verbose = _run_notice_script(tmp_path, "verbose-cache", WARPBLOB_VERBOSE="1")
    assert verbose.count(_compile.NOTICE) == 1


def test_the_command_freezes_its_imports_and_a_caller_of_main_keeps_its_own(tmp_path):
    """The ``warpblob`` command (main() with the process's arguments) freezes the objects of its imports
    before it runs; main() called by a program with its arguments leaves the program's collector alone."""
    code = textwrap.dedent(
        """
        import gc, sys
        from warpblob import cli
        sys.argv = ["warpblob", "info", "tumor"]
        before = gc.get_freeze_count()
        cli.main(["info", "tumor"])
        assert gc.get_freeze_count() == before, "main(argv) froze the caller's objects"
        cli.main()
        assert gc.get_freeze_count() > 100000, gc.get_freeze_count()
        print("ok")
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=False,
                         cwd=tmp_path)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().endswith("ok")
