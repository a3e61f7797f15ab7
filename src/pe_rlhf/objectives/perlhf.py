"""``PERLHFLoss``: the reward-free proxy-Q loss of PE-RLHF (and of HACO) as a TorchRL ``LossModule``.

One update reads a batch of transitions ``(s, a_AV, a_exec, I, I_start, C_int, s')`` and returns:

- ``loss_qvalue``: twin proxy-Q critics. TD term on the executed (behaviour) action with
  zero reward and SAC's entropy bonus,
  ``y = gamma * (1 - terminated) * (min_k Q'_k(s', a') - alpha * log pi(a'|s'))``, ``a' ~ pi(s')``,
  ``L_td = 0.5 * sum_k mean (Q_k(s, a_exec) - y)^2``; plus the CQL-style gap on takeover steps
  ``L_gap = gap_coef * sum_k mean(I * (Q_k(s, a_AV) - Q_k(s, a_exec)))`` (the paper's linear gap, at the
  agent's stored proposal ``a_AV``). The linear gap has no minimum: the critic can always lower
  ``Q(s, a_AV)`` further, and through the TD target every value sinks with it (measured: ``Q(s, a_exec)``
  drifting ~ -1 per 100 env steps when every warm-up step is a takeover, without settling);
  :class:`~pe_rlhf.objectives.ProxyValueLoss` bounds the values instead. (A hinge gap and a gap at the
  current actor's sample were options until their measurements lost: docs/results/claims/README.md.)
- ``loss_intervention_qvalue``: twin intervention critics,
  ``Q_int(s, a) <- C + gamma * (1 - terminated) * min_k Q_int'_k(s', a')`` with ``a`` the agent's
  action (the paper's equation) and ``C = I_start * (1 - cos(a_AV, a_exec))`` (or ``I_start`` with
  ``cosine_cost=False``).
- ``loss_actor``: ``alpha * log pi(a|s) - psi * min_k Q_k(s, a) + beta * min_k Q_int_k(s, a)``
  (``+ disturbance_weight * min_k Q_dist_k(s, a)`` with a disturbance critic).
- ``loss_disturbance_qvalue`` (only with a ``disturbance_qvalue_network``: HAIM-DRL): twin critics of
  the traffic-disturbance cost ``C_dist`` (``("next", "disturbance_cost")``, written by
  :class:`~pe_rlhf.transforms.TrafficDisturbanceCost`),
  ``Q_dist(s, a_exec) <- C_dist + gamma * (1 - terminated) * min_k Q_dist'_k(s', a')``, ``a' ~ pi(s')``
  (the same ``a'`` as the proxy-Q target). It is trained on the executed action, the one that braked.
- ``loss_alpha``: SAC's temperature loss towards ``target_entropy``.
- diagnostics (detached): ``alpha``, ``entropy``, ``td_loss``, ``gap_loss``, ``q_behavior``, ``q_agent``
  (0 when the batch has no takeover), ``q_intervention``, ``intervention_rate``, ``failure_rate`` (share
  of rows that end in a failure) and ``q_failure`` (mean ``Q(s, a_exec)`` on those rows, 0 when none);
  with a disturbance critic also ``q_disturbance`` (mean ``Q_dist`` at the executed actions).

Failures. A row *fails* when it is terminal and not a success (``terminated & ~success``: a crash or
leaving the road ends the episode here). With zero reward every soft value sits near
``-alpha * H / (1 - gamma)`` (hundreds below 0), so the usual terminal target 0 makes a crash worth more
than any state that drives on. ``failure_target`` says what a failure row's proxy-Q target is:
``"zero"`` (the usual terminal 0), ``"bootstrap"`` (as if the episode went on, the authors' environment,
where collisions do not end it) or ``"batch_min"`` (the lowest target of the batch's other rows: no
failure is worth more than anything else the batch holds). Successes and timeouts are unaffected, and so
is ``Q_int`` (a failure's takeover cost still ends there).

HACO is the same loss fed by an intervention transform without physics or selector; HAIM-DRL is HACO
with a disturbance critic. Without one (the default) nothing of it is built or computed: PE-RLHF's and
HACO's outputs are the same numbers as before the option existed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule, dispatch
from tensordict.utils import NestedKey
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives.common import LossModule
from torchrl.objectives.sac import compute_rsample_log_prob
from torchrl.objectives.utils import _vmap_func

from pe_rlhf.objectives.contract import KeyedLoss, TakeoverKeys, next_keys
from pe_rlhf.objectives.fused_critics import detached, evaluate, mlp_plan, project_state

FAILURE_TARGETS = ("zero", "bootstrap", "batch_min")


def _rsample_log_prob(dist) -> tuple[torch.Tensor, torch.Tensor]:
    """A reparameterised draw and the log-probability of that very draw.

    TorchRL's ``rsample_and_log_prob`` scores the pre-tanh value that made the action. Scoring the
    action afterwards (``log_prob(rsample())``) inverts the tanh of a value clamped at ``1 - 1e-6``:
    past a pre-tanh value of ~7.25 every draw is scored as 7.25, which halves the entropy of a
    saturated actor and flips the sign of the gradient on its scale (tests/objectives/test_perlhf_loss.py).
    """
    action, log_prob = compute_rsample_log_prob(dist)
    if log_prob.shape != action.shape[:-1]:  # per-dimension log-probs: sum them
        log_prob = log_prob.sum(-1)
    return action, log_prob


class PERLHFLoss(KeyedLoss, LossModule):
    """PE-RLHF's proxy-Q, CQL-style gap and intervention-cost losses (HACO and ablations as flags).

    Args:
        actor_network: a ``ProbabilisticActor`` (TanhNormal) reading ``observation`` and writing ``action``.
        qvalue_network: a ``TensorDictModule`` reading ``observation`` and ``action``, writing
            ``state_action_value``; copied into ``num_qvalue_nets`` critics with target networks.
        intervention_qvalue_network: the same for the intervention value ``Q_int`` (its own copies).
        disturbance_qvalue_network: optional, the same for HAIM-DRL's traffic-disturbance value
            ``Q_dist`` (``num_disturbance_qvalue_nets`` copies with target networks); None (default) = off.

    Keyword Args:
        gap_coef: weight of the CQL-style gap (the authors' code uses 10).
        psi, intervention_weight: the actor's weights on ``Q`` and ``Q_int`` (``beta``); 0 turns off
            "intervention minimisation".
        cosine_cost: ``False`` charges a constant 1 at each takeover start ("w/o cosine similarity").
        use_reward: add the env reward to the proxy-Q target (a reward-using variant; default off).
        gamma, alpha_init, target_entropy (``"auto"`` = -dim(action)), fixed_alpha, num_qvalue_nets.
        num_intervention_qvalue_nets: copies of ``Q_int``. 1 (default) is the paper's single intervention
            value function (parameters omega in its Algorithm 1); 2 is the authors' code (a twin, min
            over both), ~20% more time per update.
        disturbance_weight: the actor's weight on ``Q_dist`` (used with a disturbance critic).
        num_disturbance_qvalue_nets: copies of ``Q_dist`` (default 2, a twin: HAIM-DRL's own twin critic).
        failure_target: ``"batch_min"`` (default, the recipes' value), ``"zero"`` or ``"bootstrap"``: the
            proxy-Q target of rows that end in a failure (module docstring).
        fused_critics: ``True`` (default) evaluates ``make_qvalue`` critics from their stacked parameters
            (:mod:`~pe_rlhf.objectives.fused_critics`): each state's first-layer product once for every
            critic and every action it is valued at. The same values and gradients up to the order of a
            float sum. Other critic modules, batches with a multi-dimensional observation and forwards
            under autocast (``optim.precision=bf16``) go through the modules, as ``False`` always does.

    Default keys (``set_keys`` overrides): root ``observation`` (via the networks' in_keys),
    ``action`` = the agent's proposal ``a_AV`` float ``(..., A)``; under ``next`` (step outputs of the
    intervention transform): ``behavior_action`` ``(..., A)``, ``intervention`` and
    ``intervention_start`` bool ``(..., 1)``, ``intervention_cost`` float ``(..., 1)``,
    ``disturbance_cost`` float ``(..., 1)`` (read only with a disturbance critic), ``success`` bool
    ``(..., 1)`` (optional: without it every terminal row counts as a failure), and the usual
    ``reward``, ``done``, ``terminated`` ``(..., 1)``. Any batch shape (flattened to one dim); the input
    tensordict is read, never written.

    TorchRL's contract (:mod:`~pe_rlhf.objectives.contract`): ``in_keys`` lists what ``forward`` reads under the
    current keys and options, ``out_keys`` what it returns (the four ``loss_*`` terms, then the diagnostics);
    ``select_out_keys`` and keyword calls (``loss(observation=..., next_terminated=...)``) work as on
    ``SACLoss``. The targets are one-step and written out above, so ``make_value_estimator`` accepts ``TD0``
    only (its ``gamma`` becomes the loss's); any other estimator is refused with the list of supported ones.
    """

    @dataclass
    class _AcceptedKeys(TakeoverKeys):
        intervention_cost: NestedKey = ("next", "intervention_cost")
        disturbance_cost: NestedKey = ("next", "disturbance_cost")
        state_action_value: NestedKey = "state_action_value"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        success: NestedKey = ("next", "success")

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    actor_network: TensorDictModule
    qvalue_network: TensorDictModule
    intervention_qvalue_network: TensorDictModule
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams  # never created; declared so torchrl does not warn
    qvalue_network_params: TensorDictParams
    intervention_qvalue_network_params: TensorDictParams
    target_qvalue_network_params: TensorDictParams
    target_intervention_qvalue_network_params: TensorDictParams
    disturbance_qvalue_network: TensorDictModule  # only with a disturbance critic
    disturbance_qvalue_network_params: TensorDictParams
    target_disturbance_qvalue_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        qvalue_network: TensorDictModule,
        intervention_qvalue_network: TensorDictModule,
        disturbance_qvalue_network: TensorDictModule | None = None,
        *,
        num_qvalue_nets: int = 2,
        num_intervention_qvalue_nets: int = 1,
        gamma: float = 0.99,
        gap_coef: float = 10.0,
        psi: float = 1.0,
        intervention_weight: float = 1.0,
        cosine_cost: bool = True,
        use_reward: bool = False,
        alpha_init: float = 1.0,
        fixed_alpha: bool = False,
        target_entropy: float | str = "auto",
        action_dim: int | None = None,
        disturbance_weight: float = 1.0,
        num_disturbance_qvalue_nets: int = 2,
        failure_target: str = "batch_min",
        fused_critics: bool = True,
    ) -> None:
        super().__init__()
        if failure_target not in FAILURE_TARGETS:
            raise ValueError(f"PERLHFLoss failure_target={failure_target!r} is invalid; "
                             f"allowed: {list(FAILURE_TARGETS)}")
        self.failure_target = failure_target
        for name, value in (("gamma", gamma), ("gap_coef", gap_coef), ("psi", psi),
                            ("intervention_weight", intervention_weight), ("disturbance_weight", disturbance_weight)):
            if not math.isfinite(value) or value < 0 or (name == "gamma" and value > 1):
                raise ValueError(f"PERLHFLoss {name}={value} is invalid: must be finite and >= 0"
                                 + (" and <= 1" if name == "gamma" else ""))
        if not (math.isfinite(alpha_init) and alpha_init > 0):  # log(alpha_init) is the parameter
            raise ValueError(f"PERLHFLoss alpha_init={alpha_init} is invalid: must be finite and > 0")
        for name, value in (("num_qvalue_nets", num_qvalue_nets),
                            ("num_intervention_qvalue_nets", num_intervention_qvalue_nets),
                            ("num_disturbance_qvalue_nets", num_disturbance_qvalue_nets)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"PERLHFLoss {name}={value!r} is invalid: must be an int >= 1")
        if target_entropy != "auto" and (isinstance(target_entropy, (str, bool))
                                         or not math.isfinite(target_entropy)):
            raise ValueError(f"PERLHFLoss target_entropy={target_entropy!r} is invalid: 'auto' or a finite number")
        self.convert_to_functional(actor_network, "actor_network", create_target_params=False)
        self.convert_to_functional(qvalue_network, "qvalue_network", num_qvalue_nets, create_target_params=True)
        self.convert_to_functional(intervention_qvalue_network, "intervention_qvalue_network",
                                   num_intervention_qvalue_nets,
                                   create_target_params=True)
        self.num_qvalue_nets = num_qvalue_nets
        self.gamma, self.gap_coef, self.psi = gamma, gap_coef, psi
        self.intervention_weight = intervention_weight
        self.cosine_cost, self.use_reward = cosine_cost, use_reward
        if target_entropy == "auto":
            if action_dim is None:
                spec = getattr(actor_network, "spec", None)
                action_dim = spec["action"].shape[-1] if spec is not None else None
            if action_dim is None:
                raise ValueError("target_entropy='auto' needs action_dim or an actor with a spec")
            target_entropy = -float(action_dim)
        self.register_buffer("target_entropy", torch.tensor(float(target_entropy)))
        log_alpha = torch.tensor(math.log(alpha_init))
        if fixed_alpha:
            self.register_buffer("log_alpha", log_alpha)
        else:
            self.log_alpha = torch.nn.Parameter(log_alpha)
        self._vmaps = {"q": _vmap_func(self.qvalue_network, (None, 0)),
                       "q_int": _vmap_func(self.intervention_qvalue_network, (None, 0))}
        self._critic_in_keys = {"q": list(self.qvalue_network.in_keys),
                                "q_int": list(self.intervention_qvalue_network.in_keys)}
        # HAIM-DRL's disturbance critic, converted last so the other networks' copies are initialised
        # from the same random stream with or without it.
        self.has_disturbance_critic = disturbance_qvalue_network is not None
        self.disturbance_weight = float(disturbance_weight)
        if self.has_disturbance_critic:
            self.convert_to_functional(disturbance_qvalue_network, "disturbance_qvalue_network",
                                       num_disturbance_qvalue_nets, create_target_params=True)
            self._vmaps["q_dist"] = _vmap_func(self.disturbance_qvalue_network, (None, 0))
            self._critic_in_keys["q_dist"] = list(self.disturbance_qvalue_network.in_keys)
        self.fused_critics = bool(fused_critics)
        networks = {"q": "qvalue_network", "q_int": "intervention_qvalue_network",
                    "q_dist": "disturbance_qvalue_network"}
        plans = {c: mlp_plan(getattr(self, networks[c])) for c in self._vmaps} if self.fused_critics else {}
        self._plans = {c: plan for c, plan in plans.items() if plan is not None}  # the critics fused_critics applies to

    @property
    def alpha(self) -> torch.Tensor:
        return self.log_alpha.detach().exp()

    # -- TorchRL's key contract ----------------------------------------------------------------
    def _loss_in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        critics = [self.qvalue_network, self.intervention_qvalue_network]
        critics += [self.disturbance_qvalue_network] if self.has_disturbance_critic else []
        states = [k for critic in critics for k in critic.in_keys if k != keys.action]  # the loss sets the action
        step = [keys.terminated] + ([keys.reward] if self.use_reward else [])
        costs = ([keys.intervention_cost] if self.cosine_cost else []) + (
            [keys.disturbance_cost] if self.has_disturbance_critic else [])
        return [keys.action, keys.behavior_action, keys.intervention, keys.intervention_start, *costs,
                *next_keys(step), keys.success, *self.actor_network.in_keys, *states,
                *next_keys(self.actor_network.in_keys), *next_keys(states)]

    def _loss_out_keys(self) -> list[str]:
        disturbance = ["loss_disturbance_qvalue", "q_disturbance"] if self.has_disturbance_critic else []
        return ["loss_qvalue", "loss_intervention_qvalue", "loss_actor", "loss_alpha", *disturbance[:1], "alpha",
                "entropy", "td_loss", "gap_loss", "q_behavior", "q_agent", "q_intervention", "intervention_rate",
                "failure_rate", "q_failure", *disturbance[1:]]

    # -- helpers ---------------------------------------------------------------------------
    def _q(self, critic: str, params, tensordict: TensorDictBase, action: torch.Tensor) -> torch.Tensor:
        """``(copies, *batch)`` values of ``critic`` (``"q"``, ``"q_int"``, ``"q_dist"``) under ``params``
        at ``action``."""
        td = tensordict.select(*self._critic_in_keys[critic], strict=False)  # a new td: the input is not written
        td.set(self.tensor_keys.action, action)
        return self._vmaps[critic](td, params).get(self.tensor_keys.state_action_value).squeeze(-1)

    def _sample(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        with set_exploration_type(ExplorationType.RANDOM), self.actor_network_params.to_module(
            self.actor_network, preserve_module_state=False
        ):
            # only the actor's inputs: get_dist writes loc/scale, which must not land in the caller's batch
            dist = self.actor_network.get_dist(tensordict.select(*self.actor_network.in_keys, strict=False))
            return _rsample_log_prob(dist)

    def failures(self, tensordict: TensorDictBase) -> torch.Tensor:
        """Bool ``(B,)``: the rows whose step ended the episode without success (a crash, off-road)."""
        terminated = tensordict.get("next").get(self.tensor_keys.terminated).squeeze(-1).bool()
        success = tensordict.get(self.tensor_keys.success, None)
        return terminated if success is None else terminated & ~success.squeeze(-1).bool()

    def intervention_cost(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``C`` per transition ``(*batch)``: the stored cosine cost, or 1 at each start if not ``cosine_cost``."""
        start = tensordict.get(self.tensor_keys.intervention_start).squeeze(-1).float()
        if not self.cosine_cost:
            return start
        return tensordict.get(self.tensor_keys.intervention_cost).squeeze(-1).float() * start

    # -- critic values -----------------------------------------------------------------------
    def _params(self, critic: str, target: bool = False) -> TensorDictParams:
        name = {"q": "qvalue_network_params", "q_int": "intervention_qvalue_network_params",
                "q_dist": "disturbance_qvalue_network_params"}[critic]
        return getattr(self, "target_" + name if target else name)

    def _critic_values(self, tensordict: TensorDictBase, next_td: TensorDictBase, next_action: torch.Tensor,
                       new_action: torch.Tensor, takeover: torch.Tensor) -> dict[str, torch.Tensor]:
        """Every critic value one update needs, ``(copies, rows)`` each: ``next_<c>`` (target critics at
        ``(s', a')``, no grad), ``q`` (at the executed action on all rows, then at the agent's on the takeover
        rows), ``q_int`` (at the agent's action), ``q_dist`` (executed), and ``<c>_new`` (at the
        new sample, critic parameters detached), for ``c`` in ``q``, ``q_int`` (and ``q_dist``)."""
        keys = self.tensor_keys
        behavior_action, agent_action = tensordict.get(keys.behavior_action), tensordict.get(keys.action)
        actions = {"q": torch.cat([behavior_action, agent_action[takeover]], 0), "q_dist": behavior_action,
                   "q_int": agent_action}
        critics = ["q", "q_int"] + (["q_dist"] if self.has_disturbance_critic else [])
        fused = [c for c in critics if self._fusable(c, tensordict)]
        values = self._fused_values(fused, tensordict, next_td, next_action, new_action, takeover, actions)
        modules = [c for c in critics if c not in fused]
        with torch.no_grad():
            for c in modules:
                values["next_" + c] = self._q(c, self._params(c, target=True), next_td, next_action)
        for c in modules:
            td = tensordict
            if c == "q":  # the takeover rows twice: once at the executed, once at the agent's action
                state = tensordict.select(*self._critic_in_keys["q"], strict=False).exclude(keys.action)
                td = torch.cat([state, state[takeover]], 0)
            values[c] = self._q(c, self._params(c), td, actions[c])
            values[c + "_new"] = self._q(c, self._params(c).detach(), tensordict, new_action)
        return values

    def _fusable(self, critic: str, tensordict: TensorDictBase) -> bool:
        """Whether ``critic`` takes :mod:`~pe_rlhf.objectives.fused_critics`' path on this batch (docstring of
        ``fused_critics``)."""
        plan, keys = self._plans.get(critic), self.tensor_keys
        if plan is None or plan.action_key != keys.action or plan.value_key != keys.state_action_value:
            return False
        observation, action = tensordict.get(plan.observation_key, None), tensordict.get(keys.action, None)
        return (observation is not None and action is not None and observation.dim() == 2
                and observation.shape[-1] + action.shape[-1] == plan.in_features  # else the module raises
                and not torch.is_autocast_enabled(observation.device.type))

    def _fused_values(self, critics, tensordict, next_td, next_action, new_action, takeover, actions):
        """:meth:`_critic_values` of ``critics`` from their stacked parameters: each state's product with a
        critic's first layer once, reused for every action that state is valued at."""
        values = {}
        for c in critics:
            plan = self._plans[c]
            with torch.no_grad():
                target = plan.read(self._params(c, target=True))
                values["next_" + c] = evaluate(target, project_state(next_td.get(plan.observation_key), target),
                                               next_action)
            layers = plan.read(self._params(c))
            part = project_state(tensordict.get(plan.observation_key), layers)
            rows = torch.cat([part, part[:, takeover]], 1) if c == "q" else part
            values[c] = evaluate(layers, rows, actions[c])
            values[c + "_new"] = evaluate(detached(layers), part.detach(), new_action)
        return values

    # -- the loss ----------------------------------------------------------------------------
    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        keys = self.tensor_keys
        if tensordict.batch_dims != 1:  # the takeover rows are indexed along a single batch dim
            tensordict = tensordict.reshape(-1)
        next_td = tensordict.get("next")
        terminated = next_td.get(keys.terminated).squeeze(-1)
        not_terminal = 1.0 - terminated.float()
        failure = self.failures(tensordict)
        intervention = tensordict.get(keys.intervention).squeeze(-1).float()
        takeover = intervention.nonzero().squeeze(-1)
        with torch.no_grad():
            next_action, next_log_prob = self._sample(next_td)
        new_action, log_prob = self._sample(tensordict)
        values = self._critic_values(tensordict, next_td, next_action, new_action, takeover)

        with torch.no_grad():
            continuation = self.gamma * (values["next_q"].min(0)[0] - self.alpha * next_log_prob)
            if self.failure_target == "bootstrap":
                target_q = (1.0 - (terminated & ~failure).float()) * continuation
            else:
                target_q = not_terminal * continuation
            if self.use_reward:
                target_q = target_q + next_td.get(keys.reward).squeeze(-1)
            if self.failure_target == "batch_min" and failure.any() and not failure.all():
                target_q = torch.where(failure, target_q[~failure].min(), target_q)
            target_q_int = (self.intervention_cost(tensordict)
                            + self.gamma * not_terminal * values["next_q_int"].min(0)[0])

        # Q at the executed action for every transition, and at the agent's action only where the
        # mentor took over (the gap is zero elsewhere): B + n_takeover rows.
        q_all = values["q"]
        batch = tensordict.shape[0]
        q_behavior, q_agent = q_all[:, :batch], q_all[:, batch:]
        loss_td = 0.5 * (q_behavior - target_q).pow(2).mean(-1).sum(0)
        q_failure = q_behavior.detach().mean(0)[failure].mean() if failure.any() else q_all.new_zeros(())
        gap = q_agent - q_behavior[:, takeover]
        loss_gap = self.gap_coef * gap.sum(-1).sum(0) / batch

        q_int = values["q_int"]
        loss_q_int = 0.5 * (q_int - target_q_int).pow(2).mean(-1).sum(0)

        actor_terms = (self.alpha * log_prob - self.psi * values["q_new"].min(0)[0]
                       + self.intervention_weight * values["q_int_new"].min(0)[0])
        disturbance = {}
        if self.has_disturbance_critic:
            disturbance = self._disturbance_terms(tensordict, not_terminal, values)
            actor_terms = actor_terms + self.disturbance_weight * disturbance.pop("q_dist_new")
        loss_actor = actor_terms.mean()
        loss_alpha = -(self.log_alpha * (log_prob.detach() + self.target_entropy)).mean()

        return TensorDict(
            {
                "loss_qvalue": loss_td + loss_gap,
                "loss_intervention_qvalue": loss_q_int,
                "loss_actor": loss_actor,
                "loss_alpha": loss_alpha,
                "alpha": self.alpha,
                "entropy": -log_prob.detach().mean(),
                "td_loss": loss_td.detach(),
                "gap_loss": loss_gap.detach(),
                "q_behavior": q_behavior.detach().mean(),
                "q_agent": q_agent.detach().mean() if q_agent.numel() else q_all.new_zeros(()),
                "q_intervention": q_int.detach().mean(),
                "intervention_rate": intervention.mean(),
                "failure_rate": failure.float().mean(),
                "q_failure": q_failure,
                **disturbance,
            },
            batch_size=[],
        )

    def _disturbance_terms(self, tensordict: TensorDictBase, not_terminal: torch.Tensor,
                           values: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """HAIM-DRL's disturbance critic: its TD loss on the executed action, ``min_k Q_dist_k(s, a_new)``
        for the actor (critic parameters detached), and diagnostics. No sampling: the actions drawn for
        the proxy-Q target and the actor are reused, so every other term is unchanged by the option."""
        cost = tensordict.get(self.tensor_keys.disturbance_cost).squeeze(-1).float()
        with torch.no_grad():
            target = cost + self.gamma * not_terminal * values["next_q_dist"].min(0)[0]
        q_dist = values["q_dist"]
        return {"loss_disturbance_qvalue": 0.5 * (q_dist - target).pow(2).mean(-1).sum(0),
                "q_dist_new": values["q_dist_new"].min(0)[0],
                "q_disturbance": q_dist.detach().mean()}


def make_transitions(
    observation: torch.Tensor,
    next_observation: torch.Tensor,
    agent_action: torch.Tensor,
    behavior_action: torch.Tensor,
    intervention: torch.Tensor,
    intervention_start: torch.Tensor,
    terminated: torch.Tensor,
    reward: torch.Tensor | None = None,
    disturbance_cost: torch.Tensor | None = None,
) -> TensorDict:
    """A batch in the layout :class:`PERLHFLoss` reads (``(B, ...)`` tensors; flags ``(B, 1)`` bool).

    ``intervention_cost`` is computed as ``1 - cos(a_AV, a_exec)`` on start rows (0 elsewhere), as the
    intervention transform does; ``done`` copies ``terminated``; ``reward`` defaults to zeros;
    ``disturbance_cost`` ``(B, 1)`` is stored under ``next`` when given (HAIM-DRL's critic reads it).
    """
    batch = observation.shape[0]
    cost = (1 - torch.nn.functional.cosine_similarity(agent_action, behavior_action, dim=-1)).unsqueeze(-1)
    td = TensorDict(
        {
            "observation": observation,
            "action": agent_action,
            "next": {
                "observation": next_observation,
                "behavior_action": behavior_action,
                "intervention": intervention,
                "intervention_start": intervention_start,
                "intervention_cost": cost * intervention_start,
                "reward": torch.zeros(batch, 1) if reward is None else reward,
                "done": terminated.clone(),
                "terminated": terminated,
            },
        },
        [batch],
    )
    if disturbance_cost is not None:
        td.set(("next", "disturbance_cost"), disturbance_cost)
    return td
