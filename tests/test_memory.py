"""Learning on the CPU keeps freed memory for reuse (``sb3_hgrn.common.memory``): after ``learn``,
a 64 MiB allocation comes from malloc's heap instead of a fresh ``mmap``, unless the user turned it
off. Each case runs in its own process, since the setting holds for a whole process."""

import ctypes
import os
import platform
import subprocess
import sys

import pytest

from sb3_hgrn.common.memory import OPT_OUT_VARIABLE

pytestmark = pytest.mark.skipif(
    platform.libc_ver()[0] != "glibc" or not hasattr(ctypes.CDLL(None), "mallinfo2"),
    reason="malloc settings of glibc, read with its mallinfo2 (glibc 2.33 and later)",
)

LEARN_THEN_ALLOCATE = """
import ctypes
import numpy as np
from sb3_hgrn import SoftHGRN, make_graph_vec_env

class MallocInfo(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split()]

mallinfo2 = ctypes.CDLL(None).mallinfo2
mallinfo2.restype = MallocInfo
env = make_graph_vec_env("surviving_v0", n_envs=1, seed=0, env_kwargs=dict(n_agents=5, max_cycles=20))
model = SoftHGRN("GraphPolicy", env, learning_starts=40, batch_size=4, device="cpu",
                 policy_kwargs=dict(hidden_dim=16), seed=0)
model.learn(100)
mapped = mallinfo2().hblkhd
block = np.ones(64 * 2**20 // 8)
print((mallinfo2().hblkhd - mapped) // 2**20)
"""


def mapped_mib_after_learning(**environment: str) -> int:
    """MiB that a 64 MiB allocation added to malloc's ``mmap``-ed memory, after a short ``learn``."""
    done = subprocess.run(
        [sys.executable, "-c", LEARN_THEN_ALLOCATE],
        capture_output=True,
        text=True,
        env={**os.environ, **environment},
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    return int(done.stdout.split()[-1])


def test_learning_keeps_freed_memory_for_reuse():
    assert mapped_mib_after_learning() == 0


def test_the_environment_variable_turns_it_off():
    assert mapped_mib_after_learning(**{OPT_OUT_VARIABLE: "0"}) >= 64
