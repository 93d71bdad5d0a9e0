"""Shared fixtures: the devices to test on and the paths of the shared assets."""

from pathlib import Path

import pytest
import warp as wp

wp.config.quiet = True
wp.init()

# The TressFX assets live beside the checkout (../shared/data); a user's machine does not have them.
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
RATBOY = SHARED_DATA / "tressfx_ratboy"


def _devices():
    devices = ["cpu"]
    if wp.is_cuda_available():
        devices.append("cuda:0")
    return devices


@pytest.fixture(params=_devices())
def device(request):
    """Every test that takes ``device`` runs on the CPU and, when present, on the first GPU."""
    return request.param


def require_ratboy(name: str) -> Path:
    """Path of a Ratboy asset, or skip the test saying what is missing."""
    path = RATBOY / name
    if not path.exists():
        pytest.skip(f"needs the TressFX Ratboy asset {path} (shared data beside the checkout)")
    return path
