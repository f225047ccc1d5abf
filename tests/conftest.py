"""Shared fixtures: the ``device`` fixture runs a test on the CPU always and on CUDA when present."""

import os

import pytest
import warp as wp

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
wp.config.log_level = 30
wp.init()

_DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


@pytest.fixture(params=_DEVICES)
def device(request):
    return request.param
