import math

import numpy as np
import pytest
import torch as th

from sb3_hgrn import SACHGRN, evaluate_graph_policy
from sb3_hgrn.common.temperature import categorical_entropy
from tests.toy_envs import bit_vec_env, check_deployed_average, costly_tag_env, prefer_action, train_on


def quick_model(env, **kwargs):
    options = dict(
        learning_starts=64, batch_size=8, train_freq=1, policy_kwargs=dict(hidden_dim=16, n_heads=2)
    )
    options.update(kwargs)
    return SACHGRN("GraphPolicy", env, seed=0, **options)


@pytest.mark.parametrize(
    "actor_loss, tau",
    # the policy-gradient form learns this task with slowly tracking targets, not with hard copies
    [("boltzmann", 1.0), ("standard", 1.0), ("standard", 0.01), ("policy_gradient", 0.01)],
)
def test_learns_the_neighbour_bit_task(actor_loss, tau):
    model = quick_model(
        bit_vec_env(), learning_starts=256, batch_size=16, target_entropy_ratio=0.05, actor_loss=actor_loss,
        tau=tau, policy_kwargs=dict(hidden_dim=32),
    )  # fmt: skip
    model.learn(12_000)
    model.policy.drop_average()  # the loss is judged by the actor it trains, not by its lagging average
    team_return, _ = evaluate_graph_policy(model, bit_vec_env(seed=100), n_eval_episodes=16)
    assert team_return >= 29.0  # 32 is perfect; without communication 16 is the best expectation


def test_boltzmann_critic_targets_train_without_the_actors_next_logits(tmp_path, monkeypatch):
    model = quick_model(bit_vec_env(), critic_target="boltzmann")
    calls = []
    monkeypatch.setattr(model, "_next_actor_logits", lambda *args: calls.append(args))
    model.learn(200)
    assert model._n_updates > 0 and calls == []
    monkeypatch.undo()
    model.save(tmp_path / "model")
    assert SACHGRN.load(tmp_path / "model").critic_target == "boltzmann"
    del model.critic_target, model.actor_steps  # a model saved before the options trained its actor
    assert "critic_target" not in vars(model)
    model.save(tmp_path / "earlier")
    earlier = SACHGRN.load(tmp_path / "earlier")
    assert (earlier.critic_target, earlier.actor_steps) == ("actor", 1)
    assert SACHGRN.load(tmp_path / "earlier", critic_target="boltzmann").critic_target == "boltzmann"


def test_a_model_saved_before_the_behaviour_and_entropy_options_loads_with_what_it_trained_with(tmp_path):
    model = quick_model(bit_vec_env(), behaviour_policy="actor", alpha_entropy="actor").learn(100)
    del model.behaviour_policy, model.alpha_entropy  # the options of later versions
    del model.policy_kwargs["behaviour_policy"]
    model.save(tmp_path / "earlier")
    loaded = SACHGRN.load(tmp_path / "earlier")
    assert (loaded.behaviour_policy, loaded.alpha_entropy) == ("actor", "actor")
    assert loaded.policy.behaviour_policy == "actor"
    assert loaded.policy.deployed_label == model.policy.deployed_label


def test_load_refuses_a_behaviour_policy_the_saved_policy_does_not_act_with(tmp_path):
    quick_model(bit_vec_env(), behaviour_policy="critic").save(tmp_path / "model")
    assert SACHGRN.load(tmp_path / "model", behaviour_policy="critic").policy.behaviour_policy == "critic"
    with pytest.raises(ValueError, match="built with behaviour_policy='critic'; load cannot change it"):
        SACHGRN.load(tmp_path / "model", behaviour_policy="actor")
    with pytest.raises(ValueError, match="built with stochastic=True; load cannot change it to False"):
        SACHGRN.load(tmp_path / "model", stochastic=False)


def test_without_actor_steps_the_critics_and_the_deployed_policy_train_exactly_as_with_them(tmp_path):
    """With nothing reading the actor (the defaults), ``actor_steps=0`` changes no critic weight, no
    alpha and no action; the actor alone stays as it was built."""
    models = [quick_model(bit_vec_env(), actor_steps=steps).learn(240) for steps in (1, 0)]
    trained, skipped = (model.policy for model in models)
    assert models[0]._n_updates == models[1]._n_updates > 0
    for network in ("critics", "critic_targets", "critic_average"):
        ours, theirs = (getattr(policy, network).parameters() for policy in (trained, skipped))
        assert all(th.equal(a, b) for a, b in zip(ours, theirs, strict=True))
    assert th.equal(trained.temperature.alpha, skipped.temperature.alpha)
    models[1].save(tmp_path / "model")
    with pytest.raises(
        ValueError, match="actor_steps=0 leaves the actor untrained, but critic_target='actor'"
    ):
        SACHGRN.load(tmp_path / "model", critic_target="actor")
    assert SACHGRN.load(tmp_path / "model", critic_target="actor", actor_steps="auto").actor_steps == 1
    untouched = quick_model(bit_vec_env(), actor_steps=0).policy.actor.state_dict()
    assert all(th.equal(value, untouched[name]) for name, value in skipped.actor.state_dict().items())
    assert not all(th.equal(value, untouched[name]) for name, value in trained.actor.state_dict().items())


def test_auto_actor_steps_train_the_actor_only_where_something_reads_it(monkeypatch):
    """``actor_steps="auto"`` (the default) is 0 at the defaults, where nothing reads the actor, and
    the actor then runs neither in training nor in collection; each option that reads it makes it 1."""
    assert quick_model(bit_vec_env(n_envs=1)).actor_steps == 0
    for reader in (dict(behaviour_policy="actor"), dict(critic_target="actor"), dict(alpha_entropy="actor")):
        assert quick_model(bit_vec_env(n_envs=1), **reader).actor_steps == 1
    model = quick_model(bit_vec_env())
    calls = []
    monkeypatch.setattr(model.policy, "actor_logits", lambda *args: calls.append(args))
    model.learn(200)
    assert model._n_updates > 0 and calls == []
    state = model.replay_buffer.hidden[: model.replay_buffer.pos]
    actor_state = model.policy.split_state(th.as_tensor(state, dtype=th.float32))[0]
    assert not actor_state.any()  # never advanced


def test_state_holds_actor_and_critic_memories():
    """Collection advances every trained network's memory and stores it; ``predict`` runs only the
    network that chooses and returns the other parts of the state as given."""
    env = bit_vec_env(n_envs=2)
    for behaviour, chooser in (("actor", 0), ("critic", 1)):
        model = quick_model(env, behaviour_policy=behaviour, policy_kwargs=dict(hidden_dim=16, n_critics=2))
        obs = env.reset()
        _, state = model.predict(obs)
        assert state[0].shape == (1, 8, 3 * 16)
        parts = np.split(state[0][0], 3, axis=-1)
        assert [bool(np.abs(part).sum()) for part in parts] == [index == chooser for index in range(3)]
        model.learn(8 * 12)
        stored = model.replay_buffer.hidden[1 : model.replay_buffer.pos].astype(np.float32)
        assert stored.shape[-1] == 48
        actor, first, second = np.split(stored, 3, axis=-1)
        assert np.abs(first).sum() > 0 and np.abs(second).sum() > 0
        assert not np.allclose(first, second)  # separate networks, separate memories
        assert bool(np.abs(actor).sum()) == (model.actor_steps > 0)  # the critic collects: no actor


def test_exact_soft_value_and_greedy_value():
    model = quick_model(bit_vec_env(n_envs=1), critic_target="actor")
    next_q = th.tensor([[[1.0, 3.0]]])
    logits = th.log(th.tensor([[[0.25, 0.75]]]))
    alpha = th.tensor(0.5)
    expected = 0.25 * (1.0 - 0.5 * math.log(0.25)) + 0.75 * (3.0 - 0.5 * math.log(0.75))
    assert model._next_value(next_q, lambda: logits, alpha).item() == pytest.approx(expected, rel=1e-6)
    model.stochastic = False
    assert model._next_value(next_q, lambda: logits, alpha).item() == pytest.approx(3.0)


ALIVE = th.ones(1, 1)  # the one agent of the hand-computed losses lives


def test_boltzmann_actor_loss_matches_hand_computation():
    model = quick_model(bit_vec_env(n_envs=1))
    assert model.actor_loss == "boltzmann"
    logits = th.log(th.tensor([[[0.5, 0.5]]]))
    q = th.tensor([[[1.0, 2.0]]])
    target = th.softmax(q / 0.2, dim=-1)[0, 0].tolist()  # the Boltzmann policy of Q at alpha 0.2
    expected = sum(p * (math.log(p) - math.log(0.5)) for p in target)
    assert model._policy_loss(logits, q, th.tensor(0.2), ALIVE).item() == pytest.approx(expected, rel=1e-6)
    model.stochastic = False  # the greedy limit: cross-entropy to the best action
    greedy = model._policy_loss(logits, q, th.tensor(0.2), ALIVE).item()
    assert greedy == pytest.approx(-math.log(0.5), rel=1e-6)


def test_boltzmann_actor_loss_pulls_up_an_action_of_probability_near_zero():
    """The gradient on a logit is pi - softmax(Q / alpha): full size for an action the actor has
    all but dropped, where the standard loss's gradient is proportional to its probability."""
    model = quick_model(bit_vec_env(n_envs=1))
    q = th.tensor([[[0.0, 1.0]]])
    gradients = {}
    for loss in ("boltzmann", "standard"):
        model.actor_loss = loss
        logits = th.tensor([[[0.0, -20.0]]], requires_grad=True)
        model._policy_loss(logits, q, th.tensor(0.1), ALIVE).backward()
        gradients[loss] = -logits.grad[0, 0, 1].item()  # how hard a descent step raises action 1
    assert gradients["boltzmann"] > 0.99 and 0 < gradients["standard"] < 1e-7


def test_standard_actor_loss_matches_hand_computation():
    model = quick_model(bit_vec_env(n_envs=1), actor_loss="standard")
    logits = th.log(th.tensor([[[0.5, 0.5]]]))
    q = th.tensor([[[1.0, 2.0]]])
    expected = 0.5 * (0.2 * math.log(0.5) - 1.0) + 0.5 * (0.2 * math.log(0.5) - 2.0)
    assert model._policy_loss(logits, q, th.tensor(0.2), ALIVE).item() == pytest.approx(expected, rel=1e-6)


def test_save_load_round_trip(tmp_path):
    env = bit_vec_env(n_envs=2)
    model = quick_model(
        env, policy_kwargs=dict(hidden_dim=16, n_critics=2, actor_kwargs=dict(recurrent=False))
    )
    model.learn(400)
    model.save(tmp_path / "sac.zip")
    obs = env.reset()
    expected, expected_state = model.predict(obs, deterministic=True)
    actions, state = SACHGRN.load(tmp_path / "sac.zip", env=env).predict(obs, deterministic=True)
    np.testing.assert_array_equal(actions, expected)
    np.testing.assert_allclose(state[0], expected_state[0], atol=1e-6)
    assert state[0].shape == (1, 8, 32)  # actor without memory + two critics of 16
    loaded = SACHGRN.load(tmp_path / "sac.zip", env=bit_vec_env(n_envs=3))  # another copy count
    loaded.learn(12 * 10, reset_num_timesteps=False)
    assert loaded.num_timesteps == model.num_timesteps + 120


def test_logs_the_critic_loss_and_the_actor_loss_where_the_actor_trains():
    shared = ("train/critic_loss", "train/alpha", "train/entropy", "train/target_entropy")
    for actor_steps, actor_keys in (("auto", set()), (1, {"train/actor_loss", "train/actor_entropy"})):
        model = quick_model(bit_vec_env(n_envs=2), actor_steps=actor_steps)
        model.learn(8 * 20)
        logged = set(model.logger.name_to_value)
        assert set(shared) <= logged
        assert logged & {"train/actor_loss", "train/actor_entropy"} == actor_keys


def test_bad_arguments():
    with pytest.raises(ValueError, match="actor_loss"):
        quick_model(bit_vec_env(n_envs=1), actor_loss="ppo")
    with pytest.raises(ValueError, match="alpha_entropy"):
        quick_model(bit_vec_env(n_envs=1), alpha_entropy="critic")
    with pytest.raises(ValueError, match="n_critics"):
        quick_model(bit_vec_env(n_envs=1), policy_kwargs=dict(n_critics=0))
    with pytest.raises(ValueError, match="behaviour_policy"):
        quick_model(bit_vec_env(n_envs=1), behaviour_policy="random")
    with pytest.raises(ValueError, match="critic_target must be one of"):
        quick_model(bit_vec_env(n_envs=1), critic_target="critic")
    for wrong in (-1, "4", 2.0, True):
        with pytest.raises(ValueError, match=f"actor_steps must be an integer >= 0 or 'auto', got {wrong!r}"):
            quick_model(bit_vec_env(n_envs=1), actor_steps=wrong)
    for reader in (dict(behaviour_policy="actor"), dict(critic_target="actor"), dict(alpha_entropy="actor")):
        ((name, value),) = reader.items()
        with pytest.raises(ValueError, match=f"actor_steps=0 leaves the actor untrained, but {name}='actor'"):
            quick_model(bit_vec_env(n_envs=1), actor_steps=0, **reader)
    with pytest.raises(
        ValueError, match="sequence_length must be a positive integer that divides batch_size=8"
    ):
        quick_model(bit_vec_env(n_envs=1), sequence_length=3)


def test_an_own_flag_of_a_wrong_type_raises_as_a_shared_one_does():
    """SACHGRN's own arguments are checked by the mechanism that checks the shared ones."""
    with pytest.raises(TypeError, match="_init_setup_model must be true or false, got 'no'"):
        quick_model(bit_vec_env(n_envs=1), _init_setup_model="no")


def test_a_numpy_integer_is_an_integer():
    assert quick_model(bit_vec_env(n_envs=1), actor_steps=np.int64(2)).actor_steps == 2


@pytest.mark.parametrize("actor_steps", [1, 3])
def test_actor_takes_actor_steps_per_critic_step(actor_steps):
    """Each gradient step updates the critic once and the actor ``actor_steps`` times, on one batch."""
    model = quick_model(bit_vec_env(n_envs=1), actor_steps=actor_steps, learning_starts=0)
    model.learn(4 * 20)
    policy = model.policy

    def adam_steps(optimizer):
        return {int(state["step"]) for state in optimizer.state.values()}

    assert adam_steps(policy.critic_optimizer) == {model._n_updates}
    assert adam_steps(policy.actor_optimizer) == {actor_steps * model._n_updates}


@pytest.mark.parametrize("alpha_entropy", ["actor", "boltzmann"])
def test_alpha_steers_the_entropy_it_is_told(alpha_entropy):
    """With a critic whose Q-values are all 0 its Boltzmann policy is uniform (entropy log 2 for
    every agent), while the actor's entropy is whatever its initial logits give."""
    model = quick_model(bit_vec_env(n_envs=2), alpha_entropy=alpha_entropy, learning_starts=10**6)
    model.learn(8 * 10)  # fills the buffer without training
    head = model.policy.critics[0].head[0]
    with th.no_grad():
        head.weight.zero_()
        head.bias.zero_()
    steered = []
    update = model._update_temperature
    model._update_temperature = lambda entropy, groups, alive: (
        steered.append(entropy) or update(entropy, groups, alive)
    )
    model.train(gradient_steps=1, batch_size=4)
    is_uniform = th.allclose(steered[0], th.full_like(steered[0], math.log(2)))
    assert is_uniform == (alpha_entropy == "boltzmann")


@pytest.mark.parametrize("tempered, stochastic", [(True, True), (False, True), (True, False)])
def test_tempered_actor_divides_its_outputs_by_alpha(tempered, stochastic):
    """With ``tempered_actor`` the policy is ``softmax(f / alpha)`` of the actor network's outputs
    ``f``, so raising alpha makes it more random at once; a greedy (``-S``) actor is never tempered."""
    env = bit_vec_env(n_envs=1)
    policy_kwargs = dict(hidden_dim=16, tempered_actor=tempered)
    model = quick_model(env, stochastic=stochastic, policy_kwargs=policy_kwargs)
    policy = model.policy
    observations, neighbors, groups = policy.to_graphs(policy.obs_to_tensor(env.reset())[0])
    graph = policy.graph_batch(neighbors, groups)
    state = th.zeros(*observations.shape[:2], policy.actor.state_dim)
    with th.no_grad():
        outputs, _ = policy.actor(observations, graph, state)
        policy.temperature.reset(0.25)
        logits, _ = policy.actor_logits(observations, graph, state, groups)
    th.testing.assert_close(logits, outputs / 0.25 if tempered and stochastic else outputs)


def test_tempered_actor_survives_save_load(tmp_path):
    model = quick_model(bit_vec_env(n_envs=1), policy_kwargs=dict(hidden_dim=16, tempered_actor=True))
    model.save(tmp_path / "model.zip")
    assert SACHGRN.load(tmp_path / "model.zip").policy.tempered_actor is True
    assert quick_model(bit_vec_env(n_envs=1)).policy.tempered_actor is False  # the default


def test_tempered_actor_entropy_and_alpha_follow_the_target():
    """On the tag task (9 actions, target 0.3 log 9 = 0.66 nats, about 480 updates) the tempered
    actor's entropy comes within 0.5 nats of the target and alpha settles (0.010 here). An untempered
    actor stays near 1.8 nats, and alpha falls at the bound (1 % per update) all the way, to 0.0008."""
    model = train_on(
        "SACHGRN",
        costly_tag_env,
        8_000,
        target_entropy_ratio=0.3,
        alpha_entropy="actor",
        policy_kwargs=dict(tempered_actor=True),
    )
    policy, batch = model.policy, model.replay_buffer.sample(64)
    with th.no_grad():
        logits, _ = policy.actor_logits(
            batch.observations, policy.graph_batch(batch.neighbors, batch.groups),
            policy.split_state(batch.hidden)[0], batch.groups,
        )  # fmt: skip
    assert categorical_entropy(logits).mean().item() < 0.3 * math.log(9) + 0.5
    assert policy.temperature.alpha.item() > 0.003


@pytest.mark.parametrize("alpha_entropy, settles", [(None, True), ("actor", False)])
def test_alpha_settles_when_it_steers_by_the_boltzmann_entropy(alpha_entropy, settles):
    """The untempered actor of the tag task above lags its critic and stays far above the target
    entropy, so alpha steered by it falls at the bound all the way (to 0.0008). Steered by the
    entropy of the critic's Boltzmann policy (the default), alpha settles (0.015 here)."""
    kwargs = {} if alpha_entropy is None else dict(alpha_entropy=alpha_entropy)
    model = train_on("SACHGRN", costly_tag_env, 8_000, target_entropy_ratio=0.3, **kwargs)
    assert (model.policy.temperature.alpha.item() > 0.003) == settles


@pytest.mark.parametrize("behaviour_policy, preferred", [("actor", 0), ("critic", 1)])
def test_behaviour_policy_collects_and_is_deployed(behaviour_policy, preferred, tmp_path):
    """The agents collect with the actor, or with the critic's Boltzmann policy, and ``predict``
    deploys that same policy (its average), before and after a save and load."""
    env = bit_vec_env(n_envs=2)
    no_random_actions = dict(exploration_initial_eps=0.0, exploration_final_eps=0.0)
    model = quick_model(
        env, behaviour_policy=behaviour_policy, learning_starts=0, gradient_steps=0, **no_random_actions
    )
    model.policy.temperature.reset(0.5)
    prefer_action(model.policy.actor, 0)
    prefer_action(model.policy.critics[0], 1)
    model.policy.update_average()  # the deployed average's first update copies the online network
    model.learn(8 * 25)
    stored = model.replay_buffer.actions[: model.replay_buffer.pos]
    assert (stored == preferred).mean() > 0.99  # the other action has probability e^-20
    actions, _ = model.predict(env.reset())
    assert (actions == preferred).all()
    model.save(tmp_path / "model")
    loaded = SACHGRN.load(tmp_path / "model", env=env)
    assert loaded.policy.behaviour_policy == behaviour_policy
    label = "first critic (its Boltzmann policy)" if behaviour_policy == "critic" else "actor"
    assert loaded.policy.deployed_label == f"Polyak average of the {label}"
    assert (loaded.predict(env.reset())[0] == preferred).all()
    with pytest.raises(ValueError, match="policy_kwargs.behaviour_policy='actor' disagrees"):
        quick_model(env, behaviour_policy="critic", policy_kwargs=dict(behaviour_policy="actor"))


def test_critic_act_advances_every_memory_as_collection_does_and_deployment_only_the_chooser():
    env = bit_vec_env(n_envs=2)
    model = quick_model(env, behaviour_policy="actor", policy_kwargs=dict(hidden_dim=16, n_critics=2))
    policy = model.policy
    obs, _ = policy.obs_to_tensor(env.reset())
    hidden = th.randn(8, policy.state_dim)
    with th.no_grad():
        _, collected = model._behaviour_act(obs, hidden)
        actions, from_critic = policy.critic_act(obs, hidden, deterministic=True)
        _, deployed = policy.act(obs, hidden)
        observations, neighbors, groups = policy.to_graphs(obs)
        state = policy.split_state(hidden.reshape(2, 4, -1))[1]
        q_values, _ = policy.critics[0](observations, policy.graph_batch(neighbors, groups), state)
    th.testing.assert_close(from_critic, collected)
    th.testing.assert_close(actions, q_values.argmax(dim=-1).reshape(-1))
    actor, *critics = policy.split_state(deployed)
    th.testing.assert_close(actor, policy.split_state(collected)[0])  # the deployed actor chose
    for part, given in zip(critics, policy.split_state(hidden)[1:], strict=True):
        th.testing.assert_close(part, given)  # the critics did not run


def test_average_tau_deploys_an_averaged_actor_and_collects_with_the_online_one(tmp_path):
    """With ``average_tau`` every actor step moves the averaged actor, ``predict`` acts with it and the
    online actor collects; the average survives save/load."""
    env = bit_vec_env(n_envs=2)
    model = quick_model(
        env, behaviour_policy="actor", policy_kwargs=dict(hidden_dim=16, n_heads=2, average_tau=0.1)
    )
    model.learn(400)
    assert model.policy.average_network is model.policy.actor_average
    check_deployed_average(model, env, tmp_path)
