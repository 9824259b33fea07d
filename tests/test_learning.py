"""Learning tests: tiny tasks that each need one piece of the learner, run with both algorithms.

Each task is solved only when its piece works: bootstrapping through delayed rewards, stopping at
real terminations but not at time limits, using a costly but necessary action, and memory. The
docstrings of the envs in ``tests/toy_envs.py`` give the return of each way of failing.
"""

import numpy as np
import pytest
import torch as th

from tests.toy_envs import ALGORITHMS, CueMemoryEnv, InvestEnv, costly_tag_env, greedy_return, train_on


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_bootstraps_delayed_rewards_and_stops_at_terminations(algorithm):
    """Invest while a step follows, consume on the last: 2.2 per agent. Without bootstrapping an
    agent never invests (1.0); bootstrapping through the termination also invests last (1.5)."""
    model = train_on(algorithm, lambda: InvestEnv(4), 6_000, gamma=0.8)
    assert greedy_return(model, lambda: InvestEnv(4)) == pytest.approx(4 * 2.2)


@pytest.mark.parametrize("n_steps", [1, 3])
@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_bootstraps_at_time_limits(algorithm, n_steps):
    """A truncated episode goes on in the values, so investing stays right on the last step: 1.5 per
    agent. Treating the time limit as a termination consumes there (2.2). With n-step returns a
    return must also stop at the time limit and bootstrap from its final observation: summed on into
    the next episode it fails."""
    model = train_on(algorithm, lambda: InvestEnv(4, time_limit=True), 6_000, gamma=0.8, n_steps=n_steps)
    assert greedy_return(model, lambda: InvestEnv(4, time_limit=True)) == pytest.approx(4 * 1.5)


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_uses_a_costly_but_necessary_action(algorithm):
    """Tagging pays 1 with a target in reach (10 % of steps) and costs 0.5 without: on average it
    loses, so it is easy to learn to avoid it. Tagging exactly when a target is in reach earns 4 per
    team episode in expectation, never tagging 0."""
    model = train_on(algorithm, costly_tag_env, 8_000)
    assert greedy_return(model, costly_tag_env, n_episodes=32) >= 2.5


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_remembers_a_cue_with_recurrence_and_not_without(algorithm):
    """The cue is seen at the first step and asked for four steps later (1 per agent when named). With
    memory trained through time (runs of 8 steps) the model names it in every episode (seeds 0-2 all
    did, docs/results_defaults.md); without memory an agent guesses (2 per team episode in
    expectation). From stored states alone (``sequence_length=1``) both algorithms stay near chance
    at this budget."""
    make_env = lambda: CueMemoryEnv(4, delay=3)  # noqa: E731
    model = train_on(algorithm, make_env, 12_000, sequence_length=8)
    assert greedy_return(model, make_env) == pytest.approx(4.0)
    forgetful = train_on(algorithm, make_env, 12_000, sequence_length=8, policy_kwargs=dict(recurrent=False))
    assert greedy_return(forgetful, make_env, n_episodes=32) <= 2.75


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_stored_next_state_is_what_the_networks_produced(algorithm):
    """Every stored transition's next state equals the state the model's recurrent networks produce
    from its observation and stored state (no updates happen, so the networks are those that acted)."""
    extra = dict(actor_steps=1) if algorithm == "SACHGRN" else {}  # every network runs while acting
    model = train_on(algorithm, lambda: CueMemoryEnv(4, delay=1), 4 * 4 * 30, learning_starts=10**6, **extra)
    buffer, policy = model.replay_buffer, model.policy
    rows = np.repeat(np.arange(buffer.pos - 1), buffer.n_copies)
    copies = np.tile(np.arange(buffer.n_copies), buffer.pos - 1)
    batch = buffer._get_samples(rows, copies)
    states = policy.split_state(batch.hidden)
    with th.no_grad():
        produced = th.cat(
            [
                network(batch.observations, batch.neighbors, state, batch.groups)[1]
                for network, state in zip(policy.recurrent_networks, states, strict=True)
            ],
            dim=-1,
        )
    assert produced.abs().sum() > 0
    th.testing.assert_close(batch.next_hidden, produced.half().float(), atol=2e-3, rtol=0)
