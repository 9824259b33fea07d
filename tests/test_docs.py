"""The documentation site: it builds in strict mode (a broken link or anchor fails), its API
reference covers every public name, and every Python block of its pages runs."""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import os
import re
import subprocess
import sys

import pytest

import sb3_hgrn
from sb3_hgrn.common.tensorboard import AlgorithmNamedRuns
from tests.doc_snippets import DOCS, python_blocks

REPO = DOCS.parent
SITE_PACKAGES = ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python")
NOT_GUIDES = tuple(path.name for path in DOCS.glob("results*.md"))
"""Pages whose blocks are not Python to run: the measured results, with their shell commands."""
OPTIONAL = ("magent2", "mpe2", "supersuit", "pygame")
"""Packages of the ``extra`` dependencies that some pages' examples import."""
LEARN_CAP = 1_000
"""Agent-steps (env steps for a single-agent model) a page's ``learn`` call trains at most here: the
blocks check the API, not the learning."""

PAGE_SETUP = {
    "own_env.md": """
from tests.test_graph_from_positions import SwarmEnv

class MySwarm(SwarmEnv):
    agent_xy = property(lambda self: self.xy)
""",
    "graph_vec_env.md": """
from tests.toy_envs import CornerViewEnv

def make_env():
    return CornerViewEnv(n_agents=4, size=13)
""",
    "usage.md": """
import numpy as np
from sb3_hgrn import SoftHGRN, make_graph_vec_env

env = make_graph_vec_env("surviving_v0", n_envs=2, seed=0, env_kwargs={"n_agents": 10})
model = SoftHGRN("GraphPolicy", env, policy_kwargs={"hidden_dim": 16})
""",
    "single_agent.md": """
from tests.test_single_agent import ImageEnv

image_env = ImageEnv()
""",
    "reliability.md": """
from sb3_hgrn import SoftHGRN, make_graph_vec_env
from tests.toy_envs import NeighborBitEnv

def make_env():
    return NeighborBitEnv(n_agents=10)

model = SoftHGRN("GraphPolicy", make_graph_vec_env(make_env, n_envs=4, seed=0), learning_starts=100, seed=0)
""",
}
"""What a page's examples take as given (the env or model its text has built), run before its blocks."""


def pages() -> list[str]:
    return sorted(path.name for path in DOCS.glob("*.md") if path.name not in NOT_GUIDES)


def pages_with_code() -> list[str]:
    return [doc for doc in pages() if python_blocks(doc)]


def api_objects() -> list[object]:
    """The objects that the ``::: path`` entries of docs/api/*.md render."""
    objects = []
    for page in sorted((DOCS / "api").glob("*.md")):
        for path in re.findall(r"^::: ([\w.]+)$", page.read_text(encoding="utf-8"), flags=re.MULTILINE):
            module, name = path.rsplit(".", 1)
            objects.append(getattr(importlib.import_module(module), name))
    return objects


def test_site_builds_in_strict_mode(tmp_path):
    for package in SITE_PACKAGES:
        if importlib.util.find_spec(package) is None:
            pytest.skip(f"{package} is not installed: pip install -e '.[docs]' builds the site")
    site = tmp_path / "site"
    environment = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    environment["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        env=environment,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    evaluation = (site / "api" / "evaluation" / "index.html").read_text(encoding="utf-8")
    assert "RandomGraphPolicy" in evaluation and "n_eval_episodes" in evaluation  # rendered docstrings
    assert "usage: sb3-hgrn train" in (site / "api" / "cli" / "index.html").read_text(encoding="utf-8")


def test_the_api_reference_covers_every_public_name_with_a_docstring():
    documented = api_objects()
    public = [name for name in sb3_hgrn.__all__ if name != "__version__"]
    missing = [name for name in public if not any(getattr(sb3_hgrn, name) is obj for obj in documented)]
    assert missing == [], f"docs/api/*.md has no '::: module.name' entry for {missing}"
    undocumented = [getattr(obj, "__qualname__", repr(obj)) for obj in documented if not inspect.getdoc(obj)]
    assert undocumented == []


def test_every_python_block_compiles_and_says_why_when_it_is_not_run():
    blocks = [block for doc in pages() for block in python_blocks(doc)]
    assert blocks, "no python blocks found in docs/"
    for block in blocks:
        block.compiled()  # a block the tests do not run still has to be Python
        assert block.not_run is None or block.not_run.strip(), f"docs/{block.doc}:{block.line}: no reason"


@pytest.mark.parametrize("doc", pages_with_code())
def test_the_python_blocks_of_a_page_run(doc, tmp_path, monkeypatch):
    """A page's blocks run in order in one namespace, as a reader runs them, in an empty folder (with
    ``examples/`` linked in), each ``learn`` cut to :data:`LEARN_CAP` agent-steps."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "examples").symlink_to(REPO / "examples")
    learn = AlgorithmNamedRuns.learn  # every sb3_hgrn algorithm's, graph and single-agent

    def capped(self, total_timesteps, *args, **kwargs):
        return learn(self, min(total_timesteps, LEARN_CAP), *args, **kwargs)

    monkeypatch.setattr(AlgorithmNamedRuns, "learn", capped)
    namespace: dict = {"__name__": "doc_snippet"}
    exec(compile(PAGE_SETUP.get(doc, ""), f"<setup of docs/{doc}>", "exec"), namespace)
    for block in python_blocks(doc):
        if block.not_run is not None:
            continue
        try:
            exec(block.compiled(), namespace)
        except ModuleNotFoundError as error:
            if (error.name or "").split(".")[0] not in OPTIONAL:
                raise
            pytest.skip(f"docs/{doc}:{block.line} needs {error.name} (pip install -e '.[extra]')")
