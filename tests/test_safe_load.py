"""Loading model zips, replay buffers and training states never runs code from them unless trusted;
load errors name the file and the problem."""

from __future__ import annotations

import base64
import json
import pathlib
import pickle
import warnings
import zipfile
from pathlib import Path

import cloudpickle
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3 import DQN
from stable_baselines3.common import save_util
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.utils import LinearSchedule

from sb3_hgrn import SACHGRN, SoftHGRN, make_graph_vec_env
from sb3_hgrn.cli import main
from sb3_hgrn.common import safe_load
from sb3_hgrn.common.files import DamagedModelFileError, ModelFileError
from sb3_hgrn.common.safe_load import (
    RECORD_MEMBER,
    UntrustedPickleError,
    from_plain,
    restricted_loads,
    to_plain,
)
from sb3_hgrn.common.saved_controllers import ModelController
from sb3_hgrn.experiments.runs import _load_training_state, evaluate_run
from tests.toy_envs import NeighborBitEnv, SignalReaderEnv

th.set_num_threads(1)
SMALL_SURVIVING = {"n_agents": 5, "map_size": 10, "max_cycles": 5}


class Touch:
    """Unpickles into a call that creates the file ``marker``: code a pickle runs when loaded."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return pathlib.Path.touch, (self.marker,)


def bit_env(n_envs: int = 2):
    return make_graph_vec_env(NeighborBitEnv, n_envs=n_envs, seed=0)


def group_env(n_envs: int = 2):
    return make_graph_vec_env(SignalReaderEnv, n_envs=n_envs, seed=0, env_kwargs={"n_pairs": 2})


def small_model(algorithm, env, **kwargs):
    kwargs = {"learning_starts": 0, "batch_size": 4, "buffer_size": 2000, "seed": 0, **kwargs}
    policy_kwargs = {"hidden_dim": 16, "n_heads": 2, **kwargs.pop("policy_kwargs", {})}
    return algorithm("GraphPolicy", env, policy_kwargs=policy_kwargs, **kwargs)


def rewrite_zip(path: Path, members: dict[str, bytes | None]) -> None:
    """Replace (``None``: remove) members of the zip at ``path``."""
    with zipfile.ZipFile(path) as archive:
        contents = {name: archive.read(name) for name in archive.namelist()}
    contents.update(members)
    with zipfile.ZipFile(path, "w") as archive:
        for name, content in contents.items():
            if content is not None:
                archive.writestr(name, content)


def set_data_entry(path: Path, key: str, value: object, drop_record: bool = False) -> None:
    """Put ``value`` cloudpickled into the ``data`` of the zip at ``path``, as SB3 writes entries."""
    with zipfile.ZipFile(path) as archive:
        data = json.loads(archive.read("data"))
    data[key] = {
        ":type:": str(type(value)),
        ":serialized:": base64.b64encode(cloudpickle.dumps(value)).decode(),
    }
    rewrite_zip(path, {"data": json.dumps(data).encode(), **({RECORD_MEMBER: None} if drop_record else {})})


def refuse(*args, **kwargs):
    raise AssertionError("a model entry was unpickled")


@pytest.fixture
def no_full_unpickling(monkeypatch):
    """Make SB3's unpickling of zip entries fail the test."""
    monkeypatch.setattr(save_util.cloudpickle, "loads", refuse)


@pytest.fixture
def no_unpickling(monkeypatch, no_full_unpickling):
    """Make any unpickling of zip entries fail the test, the restricted one too."""
    monkeypatch.setattr(safe_load, "restricted_loads", refuse)


def assert_same_model(loaded, model, env) -> None:
    """Same predictions (and recurrent state), spaces and schedules."""
    obs = env.reset()
    expected, expected_state = model.predict(obs, deterministic=True)
    actions, state = loaded.predict(obs, deterministic=True)
    np.testing.assert_array_equal(actions, expected)
    np.testing.assert_allclose(state[0], expected_state[0], atol=1e-6)
    assert loaded.observation_space == model.observation_space
    assert loaded.action_space == model.action_space
    assert loaded.train_freq == model.train_freq
    assert loaded.policy_kwargs == model.policy_kwargs
    for progress in (1.0, 0.6, 0.1):
        assert loaded.lr_schedule(progress) == pytest.approx(model.lr_schedule(progress))
        assert loaded.exploration_schedule(progress) == pytest.approx(model.exploration_schedule(progress))


# --- Task A: nothing from the file runs unless trusted -----------------------------------------------
def test_a_pickled_payload_runs_only_with_trust(tmp_path):
    path, marker = tmp_path / "model.zip", tmp_path / "marker"
    small_model(SoftHGRN, bit_env()).save(path)
    set_data_entry(path, "payload", Touch(marker))

    with pytest.raises(UntrustedPickleError, match=rf"{path}.*payload.*pathlib.*trust_pickle=True"):
        SoftHGRN.load(path)
    assert not marker.exists()

    SoftHGRN.load(path, trust_pickle=True)
    assert marker.exists()


@pytest.mark.parametrize("key", ["policy_class", "observation_space", "lr_schedule"])
def test_a_payload_in_a_saved_entry_never_runs(tmp_path, key):
    """The record of our own zip replaces the pickled entry; a zip without one (as saved before it
    existed) refuses the payload."""
    path, marker = tmp_path / "model.zip", tmp_path / "marker"
    model = small_model(SoftHGRN, bit_env())
    model.save(path)
    set_data_entry(path, key, Touch(marker))
    assert_same_model(SoftHGRN.load(path), model, bit_env())
    assert not marker.exists()

    set_data_entry(path, key, Touch(marker), drop_record=True)
    with pytest.raises(UntrustedPickleError, match="trust_pickle"):
        SoftHGRN.load(path)
    assert not marker.exists()


def test_a_record_that_names_another_class_is_refused(tmp_path):
    path = tmp_path / "model.zip"
    small_model(SoftHGRN, bit_env()).save(path)
    with zipfile.ZipFile(path) as archive:
        record = json.loads(archive.read(RECORD_MEMBER))
    record["entries"]["policy_class"] = {"__plain__": "class", "module": "subprocess", "name": "Popen"}
    rewrite_zip(path, {RECORD_MEMBER: json.dumps(record).encode()})
    with pytest.raises(UntrustedPickleError, match="subprocess.Popen"):
        SoftHGRN.load(path)


def test_the_restricted_unpickler_never_changes_a_class():
    """A pickle that sets an attribute on an allowed class (a BUILD on the class itself)."""
    build_on_class = (
        b"\x80\x02cstable_baselines3.common.utils\nLinearSchedule\nN}X\x06\x00\x00\x00markerK\x01s\x86b."
    )
    with pytest.raises(UntrustedPickleError, match="sets attributes of the class LinearSchedule"):
        restricted_loads(build_on_class, "the file x")
    assert not hasattr(LinearSchedule, "marker")


@pytest.mark.parametrize(
    ("algorithm", "env_fn", "kwargs"),
    [
        (SoftHGRN, bit_env, {}),
        (
            SoftHGRN,
            group_env,
            {
                "learning_rate": LinearSchedule(1e-3, 1e-4, 0.5),
                "train_freq": (1, "episode"),
                "stochastic": False,
                "exploration_fraction": 0.5,
                "policy_kwargs": {"average_tau": 0.1, "optimizer_class": th.optim.RMSprop},
            },
        ),
        (SACHGRN, bit_env, {}),
        (SACHGRN, group_env, {"learning_rate": LinearSchedule(1e-3, 1e-4, 0.5), "n_steps": 2}),
    ],
)
def test_save_load_round_trip_unpickles_nothing(tmp_path, no_unpickling, algorithm, env_fn, kwargs):
    env = env_fn()
    model = small_model(algorithm, env, **kwargs)
    model.learn(8 * env.num_envs)
    path = tmp_path / "model.zip"
    model.save(path)
    for loaded in (algorithm.load(path), algorithm.load(path, env=env_fn())):
        assert_same_model(loaded, model, env_fn())
    assert algorithm.load(path, env=env_fn(), force_reset=False).num_timesteps == model.num_timesteps


def test_zips_saved_without_the_record_load_with_the_restricted_unpickler(tmp_path, no_full_unpickling):
    """As saved by the previous version: every pickled entry is one of the allowed types."""
    env = group_env()
    model = small_model(SoftHGRN, env, learning_rate=LinearSchedule(1e-3, 1e-4, 0.5), stochastic=False)
    model.learn(8 * env.num_envs)
    path = tmp_path / "model.zip"
    model.save(path)
    rewrite_zip(path, {RECORD_MEMBER: None})
    assert_same_model(SoftHGRN.load(path), model, group_env())


def test_a_learning_rate_function_needs_trust(tmp_path):
    path = tmp_path / "model.zip"
    small_model(SoftHGRN, bit_env(), learning_rate=lambda progress: 1e-3 * progress).save(path)
    with pytest.raises(UntrustedPickleError, match=rf"{path}.*'learning_rate'.*trust_pickle=True"):
        SoftHGRN.load(path)
    assert SoftHGRN.load(path, trust_pickle=True).lr_schedule(0.5) == pytest.approx(5e-4)


@pytest.mark.parametrize(
    "value",
    [
        spaces.Dict(
            {
                "obs": spaces.Box(np.array([0.0, -1.0]), np.array([1.0, np.inf]), dtype=np.float32),
                "neighbors": spaces.Box(-1, 7, shape=(3,), dtype=np.int32),
                "action_mask": spaces.MultiBinary(5),
            }
        ),
        spaces.Tuple((spaces.Discrete(4, start=1), spaces.MultiDiscrete([3, 5], start=[1, 0]))),
        (np.float32(0.5), [1, "a", None], {"x": np.arange(6).reshape(2, 3)}),
    ],
)
def test_plain_data_round_trip(value):
    restored = from_plain(json.loads(json.dumps(to_plain(value))))
    if isinstance(value, spaces.Space):
        assert restored == value
    else:
        assert restored[0] == value[0] and restored[1] == value[1]
        np.testing.assert_array_equal(restored[2]["x"], value[2]["x"])


# --- Task B -------------------------------------------------------------------------------------
def test_a_model_saved_after_drop_average_loads_and_acts_with_the_online_network(tmp_path):
    env = bit_env()
    model = small_model(SoftHGRN, env, policy_kwargs={"average_tau": 0.1})
    model.learn(8 * env.num_envs)
    model.policy.drop_average()
    model.save(tmp_path / "online.zip")
    loaded = SoftHGRN.load(tmp_path / "online.zip")
    assert loaded.policy.q_net_average is None
    assert_same_model(loaded, model, bit_env())


# --- Task C: load errors name the file and the problem -------------------------------------------
@pytest.fixture
def bad_files(tmp_path) -> dict[str, Path]:
    """A plain SB3 DQN zip, a zip whose policy.pth is cut in half, and a missing file."""
    dqn = tmp_path / "dqn.zip"
    DQN("MlpPolicy", "CartPole-v1", learning_starts=0, buffer_size=100, device="cpu").save(dqn)
    halved = tmp_path / "halved.zip"
    small_model(SoftHGRN, bit_env()).save(halved)
    with zipfile.ZipFile(halved) as archive:
        weights = archive.read("policy.pth")
    rewrite_zip(halved, {"policy.pth": weights[: len(weights) // 2]})
    return {"dqn": dqn, "halved": halved, "missing": tmp_path / "nonexistent.zip"}


LOAD_ERRORS = {
    "dqn": (ModelFileError, r"dqn.zip is not an sb3_hgrn model: it was saved by stable_baselines3's DQN"),
    "halved": (DamagedModelFileError, r"damaged model file .*halved.zip.*'policy.pth'"),
    "missing": (FileNotFoundError, r"No saved model at .*nonexistent.zip\.$"),
}


@pytest.mark.parametrize("kind", LOAD_ERRORS)
def test_load_errors_name_the_file_and_the_problem(bad_files, kind):
    error, message = LOAD_ERRORS[kind]
    with pytest.raises(error, match=message):
        SoftHGRN.load(bad_files[kind])
    with pytest.raises(ValueError if kind == "missing" else error, match=message):
        ModelController(bad_files[kind])


@pytest.mark.parametrize("command", ["evaluate", "render"])
@pytest.mark.parametrize("kind", LOAD_ERRORS)
def test_the_cli_names_the_file_and_the_problem(bad_files, kind, command, capsys):
    messages = {
        "dqn": "dqn.zip is not an sb3_hgrn model: it was saved by stable_baselines3's DQN",
        "halved": "'policy.pth'",
        "missing": "No run folder or model file at",
    }
    with pytest.raises(SystemExit) as exit_info:
        main([command, str(bad_files[kind]), "--env", "surviving_v0"])
    assert exit_info.value.code == 2
    error = capsys.readouterr().err
    assert messages[kind] in error and str(bad_files[kind]) in error and ".zip.zip" not in error


def test_the_cli_refuses_a_zip_that_needs_trust_and_loads_it_with_it(tmp_path, capsys):
    path, marker = tmp_path / "model.zip", tmp_path / "marker"
    env = make_graph_vec_env("surviving_v0", n_envs=1, env_kwargs=SMALL_SURVIVING)
    small_model(SoftHGRN, env).save(path)
    set_data_entry(path, "payload", Touch(marker))
    params = [f"{key}={value}" for key, value in SMALL_SURVIVING.items()]
    args = ["evaluate", str(path), "--env", "surviving_v0", "--episodes", "1", "--env-param", *params]
    with pytest.raises(SystemExit):
        main(args)
    assert "--trust-pickle" in capsys.readouterr().err and not marker.exists()
    assert main([*args, "--trust-pickle"]) == 0 and marker.exists()


def test_evaluate_run_loads_a_run_folder_model_with_trust_config_only(tmp_path):
    path, marker = tmp_path / "model.zip", tmp_path / "marker"
    env = make_graph_vec_env("surviving_v0", n_envs=1, env_kwargs=SMALL_SURVIVING)
    small_model(SoftHGRN, env).save(path)
    set_data_entry(path, "payload", Touch(marker))
    kwargs = {"n_episodes": 1, "env": "surviving_v0", **SMALL_SURVIVING}
    with pytest.raises(UntrustedPickleError):
        evaluate_run(path, **kwargs)
    assert not marker.exists()
    evaluate_run(path, trust_config=True, **kwargs)
    assert marker.exists()


# --- replay buffers and training states -----------------------------------------------------------
def test_replay_buffer_errors_name_the_file(tmp_path):
    env = bit_env()
    model = small_model(SoftHGRN, env)
    model.learn(4 * env.num_envs)
    good = tmp_path / "buffer.pkl"
    model.save_replay_buffer(good)
    cut = tmp_path / "cut.pkl"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    foreign = tmp_path / "foreign.pkl"
    foreign.write_bytes(pickle.dumps(ReplayBuffer(10, spaces.Box(0, 1, (2,)), spaces.Discrete(2))))
    payload, marker = tmp_path / "payload.pkl", tmp_path / "marker"
    payload.write_bytes(pickle.dumps(Touch(marker)))

    fresh = small_model(SoftHGRN, env)
    fresh.load_replay_buffer(tmp_path / "buffer")  # .pkl added, as SB3 does
    assert fresh.replay_buffer.pos == model.replay_buffer.pos
    with pytest.raises(DamagedModelFileError, match=f"damaged replay buffer file {cut}"):
        fresh.load_replay_buffer(cut)
    with pytest.raises(UntrustedPickleError, match=f"{foreign} refers to stable_baselines3.*ReplayBuffer"):
        fresh.load_replay_buffer(foreign)
    with pytest.raises(FileNotFoundError, match=r"No saved replay buffer at .*nothing.pkl\.$"):
        fresh.load_replay_buffer(tmp_path / "nothing.pkl")
    with pytest.raises(UntrustedPickleError):
        fresh.load_replay_buffer(payload)
    assert not marker.exists()
    with pytest.raises(TypeError, match="not a GraphReplayBuffer"):
        fresh.load_replay_buffer(payload, trust_pickle=True)
    assert marker.exists()


def test_a_training_state_runs_nothing_without_trust(tmp_path):
    env = bit_env()
    model = small_model(SoftHGRN, env)
    model.learn(4 * env.num_envs)
    good = tmp_path / "state.pkl"
    good.write_bytes(pickle.dumps(model.get_training_state()))
    state, marker = tmp_path / "payload.pkl", tmp_path / "marker"
    state.write_bytes(pickle.dumps({**model.get_training_state(), "env": pickle.dumps(Touch(marker))}))

    assert _load_training_state(model, good, trust_pickle=False)
    with pytest.warns(UserWarning, match=f"Skipping the training state {state}.*pathlib"):
        assert not _load_training_state(model, state, trust_pickle=False)
    assert not marker.exists()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _load_training_state(model, state, trust_pickle=True)
    assert marker.exists()
