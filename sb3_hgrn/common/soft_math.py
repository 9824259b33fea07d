"""The losses and targets of the soft algorithms, shared by the graph and the single-agent ones.

Every function works on tensors whose last axis is the action axis ``(..., n_actions)``; the leading
axes are ``(batch, n_agents)`` for the graph algorithms and ``(batch,)`` for the single-agent ones.
``mask`` arguments weigh each leading entry by 1 or 0 (the agents alive at their step; all ones
for single-agent batches). ``alpha`` is ``(1,)`` (one temperature) or ``(..., 1)`` (one per entry).
"""

from __future__ import annotations

import torch as th
import torch.nn.functional as F

from sb3_hgrn.common.temperature import categorical_entropy

ACTOR_LOSSES = ("boltzmann", "standard", "policy_gradient")
"""The discrete-SAC actor losses (see :func:`actor_loss`)."""

ALPHA_ENTROPIES = ("actor", "boltzmann")
"""The entropies a discrete-SAC temperature can steer toward its target (see :func:`steered_entropy`)."""

BEHAVIOUR_POLICIES = ("actor", "critic")
"""The policies a discrete SAC can collect with and deploy: the actor's, or the first critic's
Boltzmann policy ``softmax(Q / alpha)``."""

Q_LOSSES = ("mse", "huber")
"""The regression losses of Q-values on their targets (see :func:`q_regression_loss`)."""

CRITIC_TARGETS = ("actor", "boltzmann")
"""The policies a discrete SAC's critic targets average over at the next observations: the actor's
(:func:`sac_next_value`), or the Boltzmann policy of the target critics' minimum, whose soft
expectation is the soft value (:func:`soft_q_next_value`)."""


def masked_mean(values: th.Tensor, mask: th.Tensor) -> th.Tensor:
    """Mean of ``values`` ``(...)`` over the entries where ``mask`` (same shape, 1 or 0) is 1: the
    per-agent losses of the agents alive at their step, those of gone agents adding exactly zero
    (their values must be finite) to the value and its gradient."""
    return (values * mask).sum() / mask.sum().clamp(min=1.0)


def sample_actions(logits: th.Tensor) -> th.Tensor:
    """Actions ``(...)`` drawn from ``softmax(logits)`` ``(..., n_actions)``: the same draws from the
    same generator state as ``torch.distributions.Categorical(logits=logits).sample()``, without its
    argument checks, which wait for the device on every call. On the CPU, logits with a NaN or an inf
    (a diverged network) raise a ``ValueError`` that says so; on CUDA torch's sampler stops at a
    device-side assertion instead, since finding them first would wait for the device."""
    probs = th.softmax(logits - logits.logsumexp(dim=-1, keepdim=True), dim=-1)
    try:
        actions = th.multinomial(probs.reshape(-1, probs.shape[-1]), 1, True)
    except RuntimeError as error:  # torch's words: "probability tensor contains either inf, nan or ..."
        raise ValueError(
            "Cannot sample actions: the policy's logits are not finite (NaN or inf), so training has "
            "diverged; a lower learning_rate or max_grad_norm usually prevents it."
        ) from error
    return actions.reshape(logits.shape[:-1])


def soft_value(q_values: th.Tensor, alpha: th.Tensor) -> th.Tensor:
    """``alpha * logsumexp(Q / alpha)`` over the last axis: ``(...)`` from ``(..., n_actions)``."""
    return (alpha * th.logsumexp(q_values / alpha, dim=-1, keepdim=True)).squeeze(-1)


def soft_q_next_value(next_q: th.Tensor, alpha: th.Tensor, stochastic: bool = True) -> th.Tensor:
    """Value ``(...)`` of the next observations for soft Q-learning from target Q-values
    ``(..., n_actions)``: the soft value, or the hard max for the greedy (``stochastic=False``) variant."""
    return soft_value(next_q, alpha) if stochastic else next_q.max(dim=-1).values


def sac_next_value(
    next_q: th.Tensor, next_logits: th.Tensor, alpha: th.Tensor, stochastic: bool = True
) -> th.Tensor:
    """Value ``(...)`` of the next observations for discrete SAC from target Q-values and actor logits
    ``(..., n_actions)``: the exact soft expectation ``sum_a pi(a) (Q(a) - alpha log pi(a))`` over
    actions, or the Q-value of the actor's greedy action for ``stochastic=False``."""
    if not stochastic:
        return next_q.gather(-1, next_logits.argmax(dim=-1, keepdim=True)).squeeze(-1)
    log_probs = th.log_softmax(next_logits, dim=-1)
    return (log_probs.exp() * (next_q - alpha * log_probs)).sum(dim=-1)


def bootstrapped(
    rewards: th.Tensor, discounts: th.Tensor | float, terminated: th.Tensor, next_value: th.Tensor
) -> th.Tensor:
    """The regression target ``rewards + discounts * (1 - terminated) * next_value`` ``(...)``; with
    n-step returns ``rewards`` is the discounted sum of the steps and ``discounts`` ``gamma ** n``
    (fewer where the episode ended)."""
    return rewards + discounts * (1.0 - terminated) * next_value


def critic_minimum(q_values: list[th.Tensor]) -> th.Tensor:
    """Element-wise minimum ``(..., n_actions)`` of the Q-values of several critics."""
    return th.stack(q_values).amin(dim=0)


def q_regression_loss(
    q_values: th.Tensor, actions: th.Tensor, target: th.Tensor, mask: th.Tensor, loss: str = "mse"
) -> th.Tensor:
    """Mean error of the Q-values ``(..., n_actions)`` of the taken ``actions`` ``(..., 1)`` (int64)
    against ``target`` ``(...)`` over the entries of ``mask`` ``(...)``: squared (``"mse"``), or
    Huber's (``"huber"``: half the square up to an error of 1, linear beyond, as SB3's DQN)."""
    taken = q_values.gather(-1, actions).squeeze(-1)
    if loss == "huber":
        return masked_mean(F.smooth_l1_loss(taken, target, reduction="none"), mask)
    return masked_mean((taken - target) ** 2, mask)


def boltzmann_entropy(q_values: th.Tensor, alpha: th.Tensor) -> th.Tensor:
    """Entropy ``(...)`` in nats of the Boltzmann policy ``softmax(Q / alpha)``."""
    return categorical_entropy(q_values / alpha)


def boltzmann_divergence(log_probs: th.Tensor, q_values: th.Tensor, alpha: th.Tensor | None) -> th.Tensor:
    """``KL(softmax(Q / alpha) || pi)`` ``(...)`` from the policy's log-probabilities and Q-values
    ``(..., n_actions)``; ``alpha`` ``None`` for the greedy limit (the one-hot of the best action).

    Its gradient on the logits is ``pi - softmax(Q / alpha)``: an action whose probability has fallen
    to about zero still gets the full pull of the Boltzmann policy toward its Q-value (the gradient
    of the standard loss ``sum_a pi(a) (alpha log pi(a) - Q(a))`` shrinks with ``pi(a)``).
    """
    if alpha is None:
        target = F.one_hot(q_values.argmax(dim=-1), q_values.shape[-1]).to(log_probs.dtype)
    else:
        target = th.softmax(q_values / alpha, dim=-1)
    return (th.special.xlogy(target, target) - target * log_probs).sum(dim=-1)


def actor_loss(
    kind: str,
    logits: th.Tensor,
    q_values: th.Tensor,
    alpha: th.Tensor,
    mask: th.Tensor,
    stochastic: bool = True,
) -> th.Tensor:
    """Discrete-SAC actor loss from its logits and the (detached) critic Q-values ``(..., n_actions)``,
    averaged over the entries of ``mask`` ``(...)``. Every ``kind`` has the Boltzmann policy
    ``softmax(Q / alpha)`` as its minimiser:

    - ``"boltzmann"``: ``KL(softmax(Q / alpha) || pi)`` (:func:`boltzmann_divergence`);
    - ``"standard"``: ``sum_a pi(a) (alpha log pi(a) - Q(a))``, i.e. ``KL(pi || softmax(Q / alpha))``
      up to a constant;
    - ``"policy_gradient"``: ``-log pi(a) (Q(a) - alpha log pi(a))`` for ``a`` sampled from ``pi``.

    With ``stochastic=False`` the actor moves toward the critic's greedy action instead.
    """
    log_probs = th.log_softmax(logits, dim=-1)
    if kind == "boltzmann":
        return masked_mean(boltzmann_divergence(log_probs, q_values, alpha if stochastic else None), mask)
    alpha = alpha if stochastic else th.zeros_like(alpha)
    if kind == "standard":
        return masked_mean((log_probs.exp() * (alpha * log_probs - q_values)).sum(dim=-1), mask)
    actions = sample_actions(logits.detach()).unsqueeze(-1)
    log_prob = log_probs.gather(-1, actions)  # (..., 1), as alpha per entry
    advantage = q_values.gather(-1, actions) - alpha * log_prob.detach()
    return -masked_mean((log_prob * advantage).squeeze(-1), mask)


def steered_entropy(
    alpha_entropy: str, actor_entropy: th.Tensor | None, q_values: th.Tensor, alpha: th.Tensor
) -> th.Tensor:
    """The entropy ``(...)`` a discrete-SAC temperature follows: the actor's own (``"actor"``) or that
    of the critic's Boltzmann policy ``softmax(Q / alpha)`` (``"boltzmann"``), the policy every actor
    loss moves the actor toward."""
    return actor_entropy if alpha_entropy == "actor" else boltzmann_entropy(q_values, alpha)


def gradient_step(
    optimizer: th.optim.Optimizer, loss: th.Tensor, network: th.nn.Module, max_grad_norm: float
) -> None:
    """One optimiser step on ``loss`` with the gradient norm of ``network``'s parameters clipped to
    ``max_grad_norm``."""
    optimizer.zero_grad()
    loss.backward()
    th.nn.utils.clip_grad_norm_(network.parameters(), max_grad_norm)
    optimizer.step()
