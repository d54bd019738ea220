"""Test-session settings shared by every test file.

``make test`` runs pytest with two xdist workers on a 2-core machine: each
worker keeps torch (and OpenMP) to one thread, otherwise the workers
oversubscribe the cores and a single Q-network forward pass slows ~20x.
Rendering is headless (``MUJOCO_GL=egl``).
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402

torch.set_num_threads(1)

import pytest  # noqa: E402


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """Puts torch back to one thread after every test: a test (or a library call it makes,
    such as ultralytics' ``select_device``) that raises the count would otherwise leave the
    worker oversubscribing the two cores for every test that follows on it."""
    yield
    if torch.get_num_threads() != 1:
        torch.set_num_threads(1)
