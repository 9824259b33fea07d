"""The package layout: the env side, ``sb3_hgrn.envs``, imports no torch, no Stable-Baselines3 and no
learner code, the learner's building blocks, ``sb3_hgrn.common``, do not import the package's face, and
the top-level names of ``sb3_hgrn`` are imported only when used."""

import ast
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

import sb3_hgrn
from sb3_hgrn.common.vec_env import REGISTERED_ENVS

LEARNER_SIDE = (
    "torch",
    "stable_baselines3",
    "sb3_hgrn.common",
    "sb3_hgrn.soft_hgrn",
    "sb3_hgrn.sac_hgrn",
    "sb3_hgrn.experiments",
    "sb3_hgrn.presets",
    "sb3_hgrn.cli",
    "sb3_hgrn.analysis",
)
UNPICKLABLE_ENVS = ("pursuit_v0",)  # drives MAgent2's C engine

ENV_SIDE = """
import importlib, json, pkgutil, sys
import cloudpickle
import sb3_hgrn.envs

modules = [info.name for info in pkgutil.walk_packages(sb3_hgrn.envs.__path__, "sb3_hgrn.envs.")]
for module in modules:
    importlib.import_module(module)
envs, unpicklable = json.loads(sys.argv[1]), json.loads(sys.argv[2])
for name in envs:
    env = importlib.import_module(f"sb3_hgrn.envs.{name}").parallel_env()
    if name not in unpicklable:
        env = cloudpickle.loads(cloudpickle.dumps(env))
    env.reset(seed=0)
    env.step({agent: env.action_space(agent).sample() for agent in env.agents})
    env.neighbors()
print(json.dumps({"imported": modules, "loaded": sorted(sys.modules)}))
"""


def run_python(code: str, *args: str) -> dict:
    """Run ``code`` in a fresh interpreter; returns the JSON it prints last."""
    result = subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300, check=False
    )
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.splitlines()[-1])


def learner_modules(loaded: list[str]) -> list[str]:
    """The modules of ``loaded`` that belong to the learner side."""
    return [name for name in loaded if any(name == p or name.startswith(f"{p}.") for p in LEARNER_SIDE)]


def test_the_env_side_imports_and_runs_without_the_learner_side():
    envs = [name for name in REGISTERED_ENVS if name != "pursuit_v0" or importlib.util.find_spec("magent2")]
    report = run_python(ENV_SIDE, json.dumps(envs), json.dumps(UNPICKLABLE_ENVS))
    assert {f"sb3_hgrn.envs.{name}" for name in REGISTERED_ENVS} <= set(report["imported"])
    assert {"sb3_hgrn.envs.base", "sb3_hgrn.envs.wrappers", "sb3_hgrn.envs.position_graph"} <= set(
        report["imported"]
    )
    assert "sb3_hgrn.validation" in report["loaded"]  # the checks both halves share
    assert learner_modules(report["loaded"]) == []


def imports_of(path: Path) -> set[str]:
    """The modules a source file imports (``from a import b`` counts as ``a``), at any depth."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            names.add(node.module)
    return names


def test_no_module_of_common_imports_the_package_face():
    common = Path(sb3_hgrn.__file__).parent / "common"
    offenders = sorted(path.name for path in common.glob("*.py") if "sb3_hgrn" in imports_of(path))
    assert offenders == []


def test_top_level_names_are_imported_on_first_use():
    code = """
import json, sys
import sb3_hgrn
listed, before = dir(sb3_hgrn), sorted(sys.modules)
from sb3_hgrn import SoftHGRN, make_graph_vec_env
print(json.dumps({"listed": listed, "before": before, "after": sorted(sys.modules)}))
"""
    report = run_python(code)
    assert set(sb3_hgrn.__all__) <= set(report["listed"])
    assert learner_modules(report["before"]) == []
    assert {"torch", "sb3_hgrn.soft_hgrn", "sb3_hgrn.common.vec_env"} <= set(report["after"])


def test_top_level_names_are_those_of_their_modules():
    from sb3_hgrn.common.vec_env import make_graph_vec_env
    from sb3_hgrn.envs.wrappers import GraphFromPositions
    from sb3_hgrn.soft_hgrn import SoftHGRN

    assert sb3_hgrn.SoftHGRN is SoftHGRN and sb3_hgrn.make_graph_vec_env is make_graph_vec_env
    assert sb3_hgrn.GraphFromPositions is GraphFromPositions
    assert all(getattr(sb3_hgrn, name) is not None for name in sb3_hgrn.__all__)
    with pytest.raises(AttributeError, match="has no attribute 'NoSuchName'"):
        sb3_hgrn.NoSuchName  # noqa: B018
