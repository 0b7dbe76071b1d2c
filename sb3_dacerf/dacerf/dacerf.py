import math
from collections.abc import Callable
from typing import Any, ClassVar

import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.type_aliases import GymEnv, Schedule
from torch.nn import functional as F

from sb3_dacerf.common.policies import EnsembleCritic, twin_critic_loss
from sb3_dacerf.common.twin_critic import TwinCriticAlgorithm, frozen
from sb3_dacerf.common.validation import HyperparameterRule, integer_at_least
from sb3_dacerf.dacerf.policies import CnnPolicy, DACERFPolicy, FlowActor, MinQActionGradient, MlpPolicy, MultiInputPolicy
from sb3_dacerf.dsac.dsac import distributional_targets, gaussian_critics_loss, updated_running_std

#: The weightings of the two terms of the actor loss (``flow_matching_weights``), see :func:`actor_loss_weights`
FLOW_MATCHING_WEIGHTS = ("gain", "paper")


class DACERF(TwinCriticAlgorithm):
    """
    Diffusion Actor-Critic with Entropy Regulator via Flow matching (DACER-F), after "Real-Time Generative Policy via
    Langevin-Guided Flow Matching for Autonomous Driving" (arXiv:2603.02613).

    A flow-matching policy trained towards targets ``a*`` that Langevin dynamics on the critic (Algorithm 1) reach
    from replay actions, plus ``-Q(s, π(s))`` (:meth:`actor_loss_terms`); twin critics with target networks. This
    package's entropy regulator (after DACER's) adds ``N(0, (0.15 α)²)`` noise to stochastic actions, ``α`` learned
    towards ``target_entropy``; :data:`PAPER_HYPERPARAMETERS` holds the paper's settings.

    Its other arguments are those of SB3's ``SAC`` (``learning_rate``: of the actor, the critics and ``α``); its own:

    :param policy_delay: The actor is updated once every ``policy_delay`` critic updates
    :param langevin_steps: Number of Langevin steps ``N_l`` that turn replay actions into targets ``a*``
    :param langevin_step_size: Langevin step size ``η_a``
    :param langevin_temperature: Temperature ``α`` of the energy-based target ``exp(Q / α)``
    :param flow_matching_coef: Weight of the flow-matching (imitation) term relative to the ``-Q`` term
    :param flow_matching_weights: How the two terms of the actor loss are weighted: ``"gain"`` (free of the reward's
        scale and shift) or ``"paper"`` (the paper's weight taken literally), see :func:`actor_loss_weights`
    :param ent_coef: Entropy regulator coefficient ``α``: ``"auto"`` learns it from ``α = 3``, ``"auto_0.5"`` from
        0.5; a float fixes it; ``0`` adds no noise (the paper's mechanism)
    :param target_entropy: Target entropy of the noisy policy when ``α`` is learned; ``"auto"`` is ``-dim(A)``
    :param policy_kwargs: Arguments of :class:`~sb3_dacerf.dacerf.policies.DACERFPolicy`, e.g.
        ``dict(net_arch=[256, 256], n_sampling_steps=1, critic="layer_norm")`` (the defaults of the last two)
    :param verbose: 0 no output, 1 info, 2 debug and diagnostics: every 250 actor updates,
        ``train/imitation_to_improvement_grad`` (two extra backward passes) and, with a fixed ``α``, the entropy
        estimate and ``train/action_spread``
    """

    policy_aliases: ClassVar[dict] = dict(MlpPolicy=MlpPolicy, CnnPolicy=CnnPolicy, MultiInputPolicy=MultiInputPolicy)
    hyperparameter_rules: ClassVar[dict[str, HyperparameterRule]] = {
        **TwinCriticAlgorithm.hyperparameter_rules,
        "langevin_steps": integer_at_least(0, "an integer >= 0 (0 uses a_B as target)"),
        "langevin_step_size": HyperparameterRule(lambda value: value > 0, "> 0"),
        "langevin_temperature": HyperparameterRule(lambda value: value >= 0, ">= 0 (0 is noise-free gradient ascent)"),
        "n_sampling_steps": integer_at_least(1),  # in policy_kwargs
        "flow_matching_coef": HyperparameterRule(lambda value: value >= 0, ">= 0"),
    }
    policy: DACERFPolicy
    actor: FlowActor
    critic: EnsembleCritic
    critic_target: EnsembleCritic

    def __init__(
        self,
        policy: str | type[DACERFPolicy],
        env: GymEnv | str,
        learning_rate: float | Schedule = 3e-4,
        buffer_size: int = 1_000_000,  # 1e6
        learning_starts: int = 100,
        batch_size: int = 256,
        tau: float = 0.005,
        gamma: float = 0.99,
        train_freq: int | tuple[int, str] = 1,
        gradient_steps: int = 1,
        action_noise: ActionNoise | None = None,
        replay_buffer_class: type[ReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        optimize_memory_usage: bool = False,
        n_steps: int = 1,
        policy_delay: int = 3,
        langevin_steps: int = 20,
        langevin_step_size: float = 0.03,
        langevin_temperature: float = 0.01,
        flow_matching_coef: float = 1.0,
        flow_matching_weights: str = "gain",
        ent_coef: str | float = "auto",
        target_entropy: str | float = "auto",
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        policy_kwargs: dict[str, Any] | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ):
        super().__init__(locals())
        self.langevin_steps = langevin_steps
        self.langevin_step_size = langevin_step_size
        self.langevin_temperature = langevin_temperature
        self.flow_matching_coef = flow_matching_coef
        self.flow_matching_weights = flow_matching_weights
        self._n_actor_updates = 0
        self.running_std = None
        # The defaults written into a copy of policy_kwargs, so that a saved model records them
        self.policy_kwargs = {"n_sampling_steps": 1, "critic": "layer_norm", **self.policy_kwargs}

        if _init_setup_model:
            self._setup_model()

    def _check_hyperparameters(self) -> None:
        super()._check_hyperparameters()
        if self.flow_matching_weights not in FLOW_MATCHING_WEIGHTS:
            raise ValueError(
                f"Invalid flow_matching_weights={self.flow_matching_weights!r}: "
                f"it must be one of {', '.join(FLOW_MATCHING_WEIGHTS)}."
            )

    def _setup_model(self) -> None:
        super()._setup_model()
        self._setup_temperature(-float(get_action_dim(self.action_space)), self.lr_schedule(1))

    def _update_learning_rate(self, optimizers: list[th.optim.Optimizer] | th.optim.Optimizer) -> None:
        # The temperature's optimizer follows the learning-rate schedule too
        temperature = [] if self.ent_coef_optimizer is None else [self.ent_coef_optimizer]
        super()._update_learning_rate([*optimizers, *temperature])  # type: ignore[misc]

    def _update(self, replay_data: Any) -> dict[str, float]:
        """One iteration of Algorithm 2 (its interaction steps are ``collect_rollouts()``)."""
        # Critic update: minimise J_Q(φ_i), target y = r + γ (1 - done) min_j Q̄_j(s', a'),  a' ~ π(·|s')
        with th.no_grad():
            next_actions = self.actor(replay_data.next_observations)
        if self.critic.distributional:
            loss = self._distributional_critic_loss(replay_data, next_actions)
        else:
            loss = twin_critic_loss(self.critic, self.critic_target, replay_data, next_actions, self.gamma)
        logs = {"critic_loss": self._step(self.critic.optimizer, loss, "critic loss", replay_data)}
        # Actor update: minimise J_F(θ) (and step α), every `policy_delay` critic updates
        if self._n_updates % self.policy_delay == 0:
            logs.update(self._update_actor(replay_data))
        # Update target networks: φ̄_i <- (1 - τ) φ̄_i + τ φ_i
        self._update_targets()
        return logs

    def _distributional_critic_loss(self, replay_data: Any, next_actions: th.Tensor) -> th.Tensor:
        """DSAC-T's loss of the two Gaussian critics (:func:`~sb3_dacerf.dsac.dsac.gaussian_critics_loss`), its
        targets without an entropy term (as :func:`twin_critic_loss`'s), ``ω̄_i`` with coefficient ``tau``."""
        discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma
        with th.no_grad():
            next_means, next_stds = self.critic_target.distributions(replay_data.next_observations, next_actions)
            next_distributions = list(zip(next_means.unbind(0), next_stds.unbind(0), strict=True))
            target_mean, target_sample = distributional_targets(
                replay_data.rewards,
                (1 - replay_data.dones) * discounts,
                next_distributions,
                th.zeros_like(replay_data.rewards),
                0.0,
                [th.randn_like(mean) for mean, _ in next_distributions],
            )
        means, stds = self.critic.distributions(replay_data.observations, replay_data.actions)
        self.running_std = updated_running_std(self.running_std, stds.unbind(0), self.tau)
        distributions = list(zip(means.unbind(0), stds.unbind(0), strict=True))
        return gaussian_critics_loss(distributions, target_mean, target_sample, self.running_std)

    def langevin_targets(self, observations: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """
        The Langevin targets ``a*`` (Algorithm 1, detached) that the actor update builds from ``actions`` (in [-1, 1])
        at ``observations`` (preprocessed), with this model's ``langevin_*`` settings, on ``∇_a min_j Q_j(s, a)`` of its
        critics (which get no gradient).
        """
        with frozen(self._critic_parameters()):
            return self._langevin(MinQActionGradient(self.critic, observations), actions)

    def _langevin(self, gradient: MinQActionGradient, actions: th.Tensor) -> th.Tensor:
        steps, step_size, temperature = self.langevin_steps, self.langevin_step_size, self.langevin_temperature
        return langevin_targets(gradient, actions, steps, step_size, temperature)

    def actor_loss_terms(self, replay_data: Any) -> dict[str, th.Tensor]:
        """
        The two terms of the actor loss ``J_F`` on a replay batch (Algorithm 2), differentiable in the actor:
        ``improvement_term`` ``mean(-Q(s, π(s)) / κ)`` and ``imitation_term`` ``mean(λ_f ||v - (a* - a_0)||²)``
        (``Q = min(Q_1, Q_2)``, :func:`actor_loss_weights`); and, detached, ``kappa``, ``lambda_f``, ``flow_error``,
        ``q_values_star``, ``q_values_buffer``, the state ``features`` and the Langevin ``targets`` ``a*``.
        """
        observations, actions_buffer = replay_data.observations, replay_data.actions
        with frozen(self._critic_parameters()):
            # Langevin targets a* from the replay actions (Algorithm 1), gradients w.r.t. actions only; the critics'
            # features of the batch are computed once, there, and serve every Q below
            q_gradient = MinQActionGradient(self.critic, observations)
            actions_star = self._langevin(q_gradient, actions_buffer)
            with th.no_grad():
                q_values_star = q_gradient.min_q(actions_star)
                # Q(s, a_B) was evaluated at the loop's first step, from a_B
                q_values_buffer = q_gradient.start_min_q
                if q_values_buffer is None:  # no Langevin step (langevin_steps=0)
                    q_values_buffer = q_gradient.min_q(actions_buffer)

            # Policy improvement term: -Q(s, π_θ(s)), through the sampler from a_0 ~ N(0, I) (no exploration noise)
            features = self.actor.extract_features(observations, self.actor.features_extractor)
            actions_pi = self.actor.sample(features, self.actor.draw_noise(features))
            q_values_pi = self.critic.q_values_of_features(q_gradient.features, actions_pi).min(dim=0).values

            # Flow-matching (imitation) term ||v_θ(s, a_t, t) - (a* - a_0)||² towards a*, weighted by λ_f ∝ the gain
            kappa, lambda_f = actor_loss_weights(
                self.flow_matching_weights, q_values_star, q_values_buffer, self.flow_matching_coef
            )
            flow_error = flow_matching_loss(lambda a_t, t: self.actor.velocity(features, a_t, t), actions_star)
        return dict(
            improvement_term=(-q_values_pi / kappa).mean(),
            imitation_term=(lambda_f * flow_error).mean(),
            kappa=kappa,
            lambda_f=lambda_f,
            flow_error=flow_error.detach(),
            q_values_star=q_values_star,
            q_values_buffer=q_values_buffer,
            features=features.detach(),
            targets=actions_star,
        )

    def _update_actor(self, replay_data: Any) -> dict[str, float]:
        """One gradient step on the actor loss ``J_F`` (and on ``α`` when it is learned); returns the values to log."""
        terms = self.actor_loss_terms(replay_data)
        actor_loss = terms["improvement_term"] + terms["imitation_term"]
        logs = {"actor_loss": self._checked(actor_loss, "actor loss", replay_data)}
        self._n_actor_updates += 1
        diagnostic = self.verbose >= 2 and self._n_actor_updates % 250 == 1
        if diagnostic:
            logs["imitation_to_improvement_grad"] = self._actor_gradient_ratio(terms)

        self.actor.optimizer.zero_grad()
        actor_loss.backward()
        self.actor.optimizer.step()

        logs.update(
            flow_matching_loss=terms["flow_error"].mean().item(),
            langevin_gain=(terms["q_values_star"] - terms["q_values_buffer"]).mean().item(),
            lambda_f=terms["lambda_f"].mean().item(),
            improvement_scale=terms["kappa"].item(),
            improvement_term=terms["improvement_term"].item(),
            imitation_term=terms["imitation_term"].item(),
        )
        # Entropy regulator: estimate H of the noisy policy, then step log α (with α fixed, diagnostics)
        if self.ent_coef_optimizer is not None or diagnostic:
            logs["entropy"], logs["action_spread"] = self._entropy_and_spread(terms["features"])
        if self.ent_coef_optimizer is not None:
            logs["ent_coef_loss"] = self._update_temperature(logs["entropy"])
        return logs

    def _actor_gradient_ratio(self, terms: dict[str, th.Tensor]) -> float:
        """The norm of the imitation term's gradient on the actor's parameters over the improvement term's (``terms``
        of :meth:`actor_loss_terms`, whose graph is kept)."""
        parameters = [param for param in self.actor.parameters() if param.requires_grad]
        norms = []
        for name in ("imitation_term", "improvement_term"):
            gradients = th.autograd.grad(terms[name], parameters, retain_graph=True, allow_unused=True)
            norms.append(math.sqrt(sum(float(g.pow(2).sum()) for g in gradients if g is not None)))
        return norms[0] / max(norms[1], 1e-12)

    @th.no_grad()
    def _entropy_and_spread(self, features: th.Tensor, n_states: int = 32, n_samples: int = 8) -> tuple[float, float]:
        """The entropy of a diagonal Gaussian fitted to ``n_samples`` actions of each of ``n_states`` states, plus the
        exploration noise, and the flow's ``action_spread`` (the actions' standard deviation), averaged over the states."""
        features = features[:n_states].repeat_interleave(n_samples, dim=0)
        actions = self.actor.sample(features, self.actor.draw_noise(features))
        flow_variance = actions.view(-1, n_samples, self.actor.action_dim).var(dim=1)  # (n_states, action_dim)
        action_spread = flow_variance.sqrt().mean().item()
        variance = flow_variance + self.actor.exploration_std.pow(2)
        if not bool((variance > 0).all()):
            return -math.inf, action_spread
        entropy = 0.5 * (math.log(2 * math.pi * math.e) + variance.log()).sum(dim=1).mean().item()
        return entropy, action_spread


#: The paper's settings (its table "Training hyper-parameters") for ``DACERF(..., **PAPER_HYPERPARAMETERS)``, with its 200
#: transitions per gradient step (``n_envs`` environments: ``steps_per_gradient_kwargs(200, n_envs)`` of
#: :mod:`sb3_dacerf.common.regime`). Not from the paper: RAD's ``zeta`` and the critics.
PAPER_HYPERPARAMETERS: dict[str, Any] = dict(
    learning_rate=1e-4,
    batch_size=512,
    tau=0.001,
    gamma=0.99,
    n_steps=1,
    policy_delay=3,
    langevin_steps=20,
    langevin_step_size=0.03,
    langevin_temperature=0.01,
    flow_matching_weights="paper",
    train_freq=200,
    gradient_steps=1,
    ent_coef=0.0,
    policy_kwargs=dict(
        net_arch=[256, 256], n_sampling_steps=1, optimizer_class="RAD", optimizer_kwargs=dict(zeta=1e-16), critic="mlp"
    ),
)


def langevin_targets(
    action_gradient: Callable[[th.Tensor], th.Tensor],
    actions: th.Tensor,
    n_steps: int,
    step_size: float,
    temperature: float,
) -> th.Tensor:
    """
    Algorithm 1 of the DACER-F paper (Langevin Optimize Action): move the replay actions ``a_B`` (``actions``)
    towards samples of ``p(a|s) ∝ exp(Q(s, a) / α)`` with ``N_l`` (``n_steps``) steps
    ``a <- a + η ∇_a Q(s, a) + sqrt(2 η α) ξ``, ``ξ ~ N(0, I)``, each clipped to the action bounds [-1, 1].

    :param action_gradient: ``∇_a Q(s, a)`` of a batch of actions, the states bound inside it
    :param step_size: ``η``
    :param temperature: ``α``
    :return: The optimised actions ``a*``, detached
    """
    # ξ of every step, drawn at once and scaled by sqrt(2 η α)
    noise_scale = (2.0 * step_size * temperature) ** 0.5
    noise = th.randn((n_steps, *actions.shape), device=actions.device, dtype=actions.dtype).mul_(noise_scale)
    action = actions.detach()  # a <- a_B
    for step in range(n_steps):
        gradient = action_gradient(action)  # ∇_a Q(s, a)
        action = (action + step_size * gradient + noise[step]).clamp(-1.0, 1.0)  # a <- a + η ∇_a Q + sqrt(2ηα) ξ
    return action.detach()


def flow_matching_loss(
    velocity: Callable[[th.Tensor, th.Tensor], th.Tensor],
    targets: th.Tensor,
    noise: th.Tensor | None = None,
    time: th.Tensor | None = None,
) -> th.Tensor:
    """
    Conditional flow matching towards ``targets`` ``a*`` on the path ``a_t = (1 - t) a_0 + t a*``: each sample's error
    ``||v(a_t, t) - (a* - a_0)||²`` ``(batch, 1)``, ``velocity`` mapping ``(a_t, t)`` to ``v(s, a_t, t)``, ``a_0``
    the ``noise`` and ``t`` the ``time`` (``N(0, I)`` and ``U[0, 1]`` draws by default).
    """
    noise = th.randn_like(targets) if noise is None else noise
    time = th.rand((targets.shape[0], 1), device=targets.device, dtype=targets.dtype) if time is None else time
    actions_t = (1 - time) * noise + time * targets
    return (velocity(actions_t, time) - (targets - noise)).pow(2).sum(dim=1, keepdim=True)


def q_value_spread(q_values: th.Tensor) -> th.Tensor:
    """The mean absolute deviation of a batch of Q values (a scalar tensor): the scale ``"gain"`` weights floor ``κ`` at."""
    return (q_values - q_values.mean()).abs().mean()


def actor_loss_weights(
    method: str, q_values_star: th.Tensor, q_values_buffer: th.Tensor, coef: float = 1.0
) -> tuple[th.Tensor, th.Tensor]:
    """
    Weights of the actor loss ``J_F = mean(-Q(s, π(s)) / κ + λ_f ||v - (a* - a_0)||²)``, from the Langevin gain
    ``g = ReLU(Q(s, a*) - Q(s, a_B))`` of each sample (``q_values_star``, ``q_values_buffer``: ``(batch, 1)``):

    - ``"gain"``: ``κ = mean(g)`` (floored at ``1e-3`` of the mean absolute deviation of ``Q(s, a_B)``) and
      ``λ_f = coef · g / mean(g)``: both terms free of the reward's scale and shift.
    - ``"paper"``: ``κ = 1`` and ``λ_f = coef · g``, the paper's weight taken literally.

    :return: ``κ`` (a scalar tensor) and ``λ_f`` ``(batch, 1)``, both detached
    """
    with th.no_grad():
        gain = F.relu(q_values_star - q_values_buffer)
        mean_gain = gain.mean()
        if method == "gain":
            kappa = th.maximum(mean_gain, 1e-3 * q_value_spread(q_values_buffer)).clamp_min(1e-8)
            return kappa, coef * (gain / mean_gain.clamp_min(1e-12))
        if method == "paper":
            return th.ones_like(mean_gain), coef * gain
    raise ValueError(f"Unknown flow_matching_weights={method!r}: it must be one of {', '.join(FLOW_MATCHING_WEIGHTS)}.")
