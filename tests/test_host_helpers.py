"""Host helpers of the pipelines (``warpblob._stages``): row and column reductions that stand in for numpy's
slow reductions along the short axis of narrow arrays give numpy's values exactly; the fast host arrays are the
arrays Warp's own constructor makes."""

import numpy as np
import pytest
import warp as wp

from warpblob._stages import column_bounds, device_array, device_empty, head, host_array, rows_all, rows_any


@pytest.mark.parametrize("dtype", [bool, np.uint8, np.int8, np.int32, np.float64])
@pytest.mark.parametrize("width", range(10))
def test_row_reductions_are_numpys(dtype, width):
    """Every width (the 1-, 2-, 4- and 8-byte rows read as words, the others by columns), every dtype, and a
    view that is not contiguous: the same as ``any(axis=1)`` and ``all(axis=1)``."""
    rng = np.random.default_rng(width)
    a = rng.integers(-2, 3, (517, width)).astype(dtype)
    a[::7] = 0  # rows of zeros
    a[1::7] = 1  # rows with none
    for arr in (a, a[:, ::-1], a[::2]):
        np.testing.assert_array_equal(rows_any(arr), arr.any(axis=1))
        np.testing.assert_array_equal(rows_all(arr), arr.all(axis=1))


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int64])
def test_column_bounds_are_numpys(dtype):
    rng = np.random.default_rng(3)
    a = (rng.standard_normal((1001, 3)) * 100).astype(dtype)
    low, high = column_bounds(a)
    np.testing.assert_array_equal(low, a.min(axis=0))
    np.testing.assert_array_equal(high, a.max(axis=0))
    assert low.dtype == a.dtype == high.dtype


# -- fast host arrays: the state Warp's own constructor gives ------------------------------------------------------

_KINDS = [  # (numpy dtype, trailing shape, Warp dtype)
    (np.int32, (), wp.int32), (np.uint8, (), wp.uint8), (np.int64, (), wp.int64), (np.float32, (), wp.float32),
    (np.float64, (), wp.float64), (np.float32, (), float), (np.int32, (2,), wp.vec2i), (np.int32, (4,), wp.vec4i),
    (np.float32, (3,), wp.vec3), (np.float64, (3,), wp.vec3d), (np.float32, (3, 3), wp.mat33),
]


def _state(arr: wp.array) -> dict:
    return {k: v for k, v in vars(arr).items()}


@pytest.mark.parametrize("np_dtype, inner, dtype", _KINDS)
def test_host_array_is_the_array_warp_makes(np_dtype, inner, dtype):
    """For 1-D and 2-D arrays of every kind, of several lengths, writable and read-only, views into a larger
    array included: every attribute equals that of ``wp.array(values, copy=False)`` (the fast path's first
    array of a kind is Warp's own; the later ones are copied from it), and a kernel reads the values."""
    rng = np.random.default_rng(len(inner))
    for outer in ((1,), (7,), (1000,), (5, 3)):
        big = (rng.standard_normal((2 * int(np.prod(outer)) + 3, *inner)) * 50).astype(np_dtype)
        flat = big[3 : 3 + int(np.prod(outer))]
        values = flat.reshape(*outer, *inner)
        for v in (values, values.copy()):
            if v is not values:
                v.flags.writeable = False
            fast = host_array(v, dtype)
            slow = wp.array(v, dtype=dtype, device="cpu", copy=False)
            assert _state(fast).keys() == _state(slow).keys()
            for k in _state(slow):
                assert _state(fast)[k] is _state(slow)[k] or _state(fast)[k] == _state(slow)[k], k
            np.testing.assert_array_equal(fast.numpy(), v)


def test_host_arrays_warp_does_not_cover_go_through_warp():
    """Not C-contiguous, empty, another numpy dtype (converted by Warp), a flat array of vectors: Warp's own
    result, values included."""
    a = np.arange(24, dtype=np.int32)
    for values, dtype in ((a[::2], wp.int32), (a[:0], wp.int32), (a.reshape(8, 3), wp.vec3i), (a, wp.vec3i)):
        fast, slow = host_array(values, dtype), wp.array(values, dtype=dtype, device="cpu", copy=False)
        assert fast.shape == slow.shape and fast.dtype == slow.dtype and fast.strides == slow.strides
        np.testing.assert_array_equal(fast.numpy(), slow.numpy())


@wp.kernel
def _double_kernel(a: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = 2.0 * a[i]


def test_fast_host_arrays_share_and_keep_their_memory():
    """A kernel reads and writes the numpy arrays' own memory through the fast arrays, and an array keeps its
    numpy memory alive after the caller drops it; ``head`` is ``base[:n]`` (attributes and memory)."""
    import gc

    values = np.arange(30, dtype=np.float32).reshape(10, 3)
    out = np.zeros_like(values)
    a = host_array(values.copy(), wp.vec3)  # (the copy's only owner is the Warp array)
    gc.collect()
    wp.launch(_double_kernel, 10, inputs=[a, host_array(out, wp.vec3)], device="cpu")
    np.testing.assert_array_equal(out, 2 * values)
    base = device_empty(12, wp.vec3, "cpu", zero=True)
    assert np.all(base.numpy() == 0) and base.shape == (12,)
    for n in (1, 5, 12):
        h, s = head(base, n), base[:n]
        assert _state(h).keys() == _state(s).keys()
        for k in _state(s):
            assert _state(h)[k] is _state(s)[k] or _state(h)[k] == _state(s)[k], k
    wp.launch(_double_kernel, 5, inputs=[a, head(base, 5)], device="cpu")
    np.testing.assert_array_equal(base.numpy()[:5], 2 * values[:5])
    np.testing.assert_array_equal(base.numpy()[5:], 0)
    copied = device_array(values, wp.vec3, "cpu")
    values[0] = -1.0
    assert copied.numpy()[0, 0] == 0.0  # a copy by default
    assert device_array(values, wp.vec3, "cpu", copy=False).numpy()[0, 0] == -1.0  # shared without
