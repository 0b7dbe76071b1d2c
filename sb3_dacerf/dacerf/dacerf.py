import math
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np
import torch as th
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.preprocessing import get_action_dim
from stable_baselines3.common.type_aliases import GymEnv, Schedule
from torch.nn import functional as F

from sb3_dacerf.common.policies import EnsembleCritic, twin_critic_loss
from sb3_dacerf.common.twin_critic import TwinCriticAlgorithm, frozen
from sb3_dacerf.common.validation import HyperparameterRule, integer_at_least, made_env
from sb3_dacerf.dacerf.policies import CnnPolicy, DACERFPolicy, FlowActor, MinQActionGradient, MlpPolicy, MultiInputPolicy

#: The weightings of the two terms of the actor loss (``flow_matching_weights``), see :func:`actor_loss_weights`
FLOW_MATCHING_WEIGHTS = ("gain", "paper")


class DACERF(TwinCriticAlgorithm):
    """
    Diffusion Actor-Critic with Entropy Regulator via Flow matching (DACER-F).

    A flow-matching policy that generates an action in one Euler step, trained towards targets ``a*``
    obtained by Langevin dynamics on the critic (``p(a|s) ∝ exp(Q(s, a) / α)``) started from replay actions,
    plus the usual ``-Q(s, π(s))`` improvement term; twin critics with target networks as in TD3/SAC.
    Paper: "Real-Time Generative Policy via Langevin-Guided Flow Matching for Autonomous Driving" (DACER-F),
    arXiv:2603.02613.

    The actor loss is ``J_F = mean(-Q(s, π(s)) / κ + λ_f ||v(s, a_t, t) - (a* - a_0)||²)`` with the paper's
    advantage weighting ``λ_f ∝ g = ReLU(Q(s, a*) - Q(s, a_B))`` per sample, normalised by its batch mean; by default
    (``flow_matching_weights="gain"``) the improvement term is expressed in units of the batch's mean Langevin gain
    (``κ = mean(g)``), so that the balance of the two terms does not depend on the reward's scale or shift
    (see :func:`actor_loss_weights`).
    Every Q above is ``min(Q_1, Q_2)``, the same pessimistic estimate as in the Bellman target.

    Entropy regulator (this package's, after DACER's; the DACER-F paper describes none): a flow sampled in one Euler
    step from independent noise tends to a deterministic policy, so stochastic actions get Gaussian noise
    ``N(0, (0.15 α)²)`` on top, during rollouts and for the next action ``a'`` of the critic target. ``α`` is learned
    (``ent_coef="auto"``) towards ``target_entropy`` with SAC's temperature loss on an entropy estimate of the noisy
    policy. Deterministic actions (``predict(..., deterministic=True)``, exported graphs) are noise-free. ``ent_coef=0``
    is the paper's exact mechanism (no added noise); :data:`PAPER_HYPERPARAMETERS` holds the settings the paper gives.

    :param policy: The policy model to use (MlpPolicy, CnnPolicy, ...)
    :param env: The environment to learn from (if registered in Gym, can be str)
    :param learning_rate: learning rate for the optimizer of the actor and of the critics,
        it can be a function of the current progress remaining (from 1 to 0)
    :param buffer_size: size of the replay buffer
    :param learning_starts: how many steps of the model to collect transitions for before learning starts
    :param batch_size: Minibatch size for each gradient update
    :param tau: the soft update coefficient ("Polyak update", between 0 and 1)
    :param gamma: the discount factor
    :param train_freq: Update the model every ``train_freq`` steps. Alternatively pass a tuple of frequency and unit
        like ``(5, "step")`` or ``(2, "episode")``.
    :param gradient_steps: How many gradient steps to do after each rollout (see ``train_freq``)
        Set to ``-1`` means to do as many gradient steps as steps done in the environment
        during the rollout.
    :param action_noise: the action noise type (None by default), added to the flow policy's own samples
        during rollouts (extra exploration, see "Exploration with a one-step flow" in the DACERF documentation page)
    :param replay_buffer_class: Replay buffer class to use (for instance ``HerReplayBuffer``).
        If ``None``, it will be automatically selected.
    :param replay_buffer_kwargs: Keyword arguments to pass to the replay buffer on creation.
    :param optimize_memory_usage: Enable a memory efficient variant of the replay buffer
        at a cost of more complexity.
    :param n_steps: Rewards summed in the critic target before it bootstraps: 1 (the default) is the paper's
        one-step target; more uses n-step returns (SB3's ``NStepReplayBuffer``)
    :param policy_delay: The actor is updated once every ``policy_delay`` critic updates
    :param langevin_steps: Number of Langevin steps ``N_l`` that turn replay actions into targets ``a*``
    :param langevin_step_size: Langevin step size ``η_a``
    :param langevin_temperature: Temperature ``α`` of the energy-based target ``exp(Q / α)``
    :param langevin_normalize_gradient: Divide ``∇_a Q`` by ``max(1, mean |∇_a Q|)`` over the batch in every Langevin
        step, so that a step moves a coordinate by ``η_a`` on average at most whatever the reward's scale (off:
        the paper's update, whose steps grow with the rewards; with returns in the thousands most targets then
        sit at the action bounds)
    :param flow_matching_coef: Weight of the flow-matching (imitation) term relative to the ``-Q`` term
    :param flow_matching_weights: How the two terms of the actor loss are weighted: ``"gain"`` (scale- and
        shift-free, the default) or ``"paper"`` (``λ_f = flow_matching_coef · ReLU(Q(s, a*) - Q(s, a_B))``, the
        paper's weight taken literally, and the paper preset's), see :func:`actor_loss_weights`
    :param ent_coef: Entropy regulator coefficient ``α``, the exploration noise being ``N(0, (0.15 α)²)``.
        ``"auto"`` learns it starting from ``α = 3`` (DACER's initial value), ``"auto_0.5"`` starting from 0.5;
        a float fixes it; ``0`` adds no noise (the paper's mechanism)
    :param target_entropy: Target entropy of the noisy policy when ``α`` is learned; ``"auto"`` is ``-dim(A)``
        (SAC's choice)
    :param stats_window_size: Window size for the rollout logging, specifying the number of episodes to average
        the reported success rate, mean episode length, and mean reward over
    :param tensorboard_log: the log location for tensorboard (if None, no logging)
    :param policy_kwargs: additional arguments to be passed to the policy on creation, e.g.
        ``dict(net_arch=[256, 256], n_sampling_steps=1, critic="layer_norm")``: ``n_sampling_steps`` is the number
        of Euler steps of the flow sampler (1, the paper's, by default: one network call per action); ``critic`` is
        ``"layer_norm"`` (``LayerNorm`` after every hidden layer) by default, ``"mlp"`` for SB3's MLP critics or
        ``"batch_renorm"`` for CrossQ's batch-renorm critics, without target networks (``tau`` is then unused); see
        :class:`~sb3_dacerf.dacerf.policies.DACERFPolicy` for the others
    :param verbose: Verbosity level: 0 for no output, 1 for info messages (such as device or wrappers used), 2 for
        debug messages and diagnostics: every 250 actor updates, ``train/imitation_to_improvement_grad`` (the ratio of
        the gradient norms of the two terms of the actor loss, two extra backward passes) and, with a fixed ``α``, the
        entropy estimate and ``train/action_spread``
    :param seed: Seed for the pseudo random generators
    :param device: Device (cpu, cuda, ...) on which the code should be run.
        Setting it to auto, the code will be run on the GPU if possible.
    :param _init_setup_model: Whether or not to build the network at the creation of the instance
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    #: DACER-F's own hyper-parameters with their valid values, besides those of every algorithm of the package
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
        langevin_normalize_gradient: bool = False,
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
        super().__init__(
            policy,
            made_env(env, type(self).__name__, verbose),  # type: ignore[arg-type]  # SB3's load() passes env=None
            learning_rate,
            buffer_size=buffer_size,
            learning_starts=learning_starts,
            batch_size=batch_size,
            tau=tau,
            gamma=gamma,
            train_freq=train_freq,
            gradient_steps=gradient_steps,
            action_noise=action_noise,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=optimize_memory_usage,
            n_steps=n_steps,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            policy_kwargs=policy_kwargs,
            verbose=verbose,
            seed=seed,
            device=device,
            supported_action_spaces=None,  # made_env() checked it, with an error that says what to do instead
            support_multi_env=True,
            sde_support=False,
        )

        # DACER-F's own hyper-parameters (Algorithm 2)
        self.policy_delay = policy_delay
        self.langevin_steps = langevin_steps
        self.langevin_step_size = langevin_step_size
        self.langevin_temperature = langevin_temperature
        self.langevin_normalize_gradient = langevin_normalize_gradient
        self.flow_matching_coef = flow_matching_coef
        self.flow_matching_weights = flow_matching_weights
        # Entropy regulator
        self.ent_coef = ent_coef
        self.target_entropy = target_entropy
        self._n_actor_updates = 0
        # One Euler step and LayerNorm critics unless policy_kwargs say otherwise, written into a copy of
        # policy_kwargs (the caller's dict stays reusable), so that a saved model records them
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
        self._setup_temperature(self.actor.log_alpha, -float(get_action_dim(self.action_space)), self.lr_schedule(1))

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        # Switch to train mode (this affects batch norm / dropout)
        self.policy.set_training_mode(True)
        optimizers = [self.actor.optimizer, self.critic.optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers.append(self.ent_coef_optimizer)
        self._update_learning_rate(optimizers)
        assert self.replay_buffer is not None, "train() needs the replay buffer that _setup_model() creates"

        critic_losses: list[float] = []
        actor_logs: dict[str, list[float]] = {}

        # One iteration of Algorithm 2 per gradient step (the interaction steps are collect_rollouts())
        for _ in range(gradient_steps):
            self._n_updates += 1
            # Replay: sample a batch (s, a_B, r, s', done) from the buffer B, actions a_B in [-1, 1]
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)

            # Critic update: minimise J_Q(φ_i), target y = r + γ (1 - done) min_j Q̄_j(s', a'),  a' ~ π(·|s')
            with th.no_grad():
                next_actions = self.actor(replay_data.next_observations)
            critic_loss = twin_critic_loss(self.critic, self.critic_target, replay_data, next_actions, self.gamma)
            critic_losses.append(self._step(self.critic.optimizer, critic_loss, "critic loss", replay_data))

            # Actor update: minimise J_F(θ) (and step α), every `policy_delay` critic updates
            if self._n_updates % self.policy_delay == 0:
                for key, value in self._update_actor(replay_data).items():
                    actor_logs.setdefault(key, []).append(value)

            # Update target networks: φ̄_i <- (1 - τ) φ̄_i + τ φ_i
            self._update_targets()

        self.logger.record("train/n_updates", self._n_updates)
        self.logger.record("train/critic_loss", np.mean(critic_losses))
        self.logger.record("train/ent_coef", self.actor.log_alpha.exp().item())
        for key, values in actor_logs.items():
            finite = [value for value in values if math.isfinite(value)]
            if finite:
                self.logger.record(f"train/{key}", np.mean(finite))

    def langevin_targets(self, observations: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """
        The Langevin targets ``a*`` (Algorithm 1) that the actor update builds from ``actions`` at ``observations``,
        with this model's ``langevin_*`` settings, on ``∇_a min_j Q_j(s, a)`` of its critics (which get no gradient).

        :param observations: A batch of (preprocessed) observations
        :param actions: The starting actions, in the policy's [-1, 1] space, one per observation
        :return: ``a*``, detached, the shape of ``actions``
        """
        return self._langevin(observations, actions)[0]

    def _langevin(self, observations: th.Tensor, actions: th.Tensor) -> tuple[th.Tensor, MinQActionGradient]:
        """:meth:`langevin_targets`, and the ``∇_a min Q`` it used (its features and ``start_min_q``)."""
        with frozen(self._critic_parameters()):
            gradient = MinQActionGradient(self.critic, observations)
            targets = langevin_targets(
                gradient,
                actions,
                n_steps=self.langevin_steps,
                step_size=self.langevin_step_size,
                temperature=self.langevin_temperature,
                normalize_gradient=self.langevin_normalize_gradient,
            )
        return targets, gradient

    def actor_loss_terms(self, replay_data: Any) -> dict[str, th.Tensor]:
        """
        The two terms of the actor loss ``J_F`` on a replay batch (Algorithm 2), with what they are made of.

        :param replay_data: A batch of the replay buffer
        :return: ``improvement_term`` (``mean(-Q(s, π(s)) / κ)``) and ``imitation_term``
            (``mean(λ_f ||v - (a* - a_0)||²)``), both differentiable with respect to the actor, and (detached)
            ``kappa``, ``lambda_f``, ``flow_error``, ``q_values_star``, ``q_values_buffer``, the state ``features``
            and the flow-matching ``targets`` (``a*``, unless the batch chose others: :meth:`imitation_targets`)
        """
        observations, actions_buffer = replay_data.observations, replay_data.actions
        with frozen(self._critic_parameters()):
            # Langevin targets a* from the replay actions (Algorithm 1), gradients w.r.t. actions only; the critics'
            # features of the batch are computed once, there, and serve every Q below
            actions_star, q_gradient = self._langevin(observations, actions_buffer)
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
            targets, lambda_f = self.imitation_targets(replay_data, actions_star, lambda_f)
            flow_error = flow_matching_loss(lambda a_t, t: self.actor.velocity(features, a_t, t), targets)
        return dict(
            improvement_term=(-q_values_pi / kappa).mean(),
            imitation_term=(lambda_f * flow_error).mean(),
            kappa=kappa,
            lambda_f=lambda_f,
            flow_error=flow_error.detach(),
            q_values_star=q_values_star,
            q_values_buffer=q_values_buffer,
            features=features.detach(),
            targets=targets,
        )

    @staticmethod
    def imitation_targets(replay_data: Any, targets: th.Tensor, weights: th.Tensor) -> tuple[th.Tensor, th.Tensor]:
        """
        The flow-matching targets of a batch and their weights: the Langevin targets ``a*`` with the weights ``λ_f``,
        unless the batch has an ``imitation_targets(targets, weights)`` method of its own, which then decides (the
        batches of a :class:`~sb3_dacerf.common.buffers.DemonstrationReplayBuffer` with
        ``demonstration_targets="actions"`` put the demonstrated actions in place of the demonstrations' ``a*``).

        :param replay_data: A batch of the replay buffer
        :param targets: The Langevin targets ``a*`` of the batch ``(batch, action_dim)``
        :param weights: Their weights ``λ_f`` ``(batch, 1)``
        :return: The targets and weights the imitation term fits
        """
        choose = getattr(replay_data, "imitation_targets", None)
        return (targets, weights) if choose is None else choose(targets, weights)

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
        # Entropy regulator: estimate H of the noisy policy, then step log α on J(α) = log α (H - H_target), whose
        # gradient shrinks the noise while the policy is more random than the target. With α fixed the estimate and
        # the flow's spread are diagnostics
        if self.ent_coef_optimizer is not None or diagnostic:
            logs["entropy"], logs["action_spread"] = self._entropy_and_spread(terms["features"])
        if self.ent_coef_optimizer is not None:
            ent_coef_loss = self.actor.log_alpha * (logs["entropy"] - float(self.target_entropy))
            self.ent_coef_optimizer.zero_grad()
            ent_coef_loss.backward()
            self.ent_coef_optimizer.step()
            logs["ent_coef_loss"] = self.actor.log_alpha.item() * (logs["entropy"] - float(self.target_entropy))
        return logs

    def _actor_gradient_ratio(self, terms: dict[str, th.Tensor]) -> float:
        """
        Balance of the actor loss: the norm of the imitation term's gradient on the actor's parameters over that of
        the improvement term's (1: equal pull; logged as ``train/imitation_to_improvement_grad``).

        :param terms: The output of :meth:`actor_loss_terms` (its graph is kept for a later ``backward``)
        """
        parameters = [param for param in self.actor.parameters() if param.requires_grad]
        norms = []
        for name in ("imitation_term", "improvement_term"):
            gradients = th.autograd.grad(terms[name], parameters, retain_graph=True, allow_unused=True)
            norms.append(math.sqrt(sum(float(g.pow(2).sum()) for g in gradients if g is not None)))
        return norms[0] / max(norms[1], 1e-12)

    @th.no_grad()
    def _entropy_and_spread(self, features: th.Tensor, n_states: int = 32, n_samples: int = 8) -> tuple[float, float]:
        """
        Entropy estimate of the noisy policy and the flow's own ``action_spread``. The flow is sampled with
        ``n_samples`` noises ``a_0`` at each of ``n_states`` states of the batch; a diagonal Gaussian fitted to each
        state's actions, plus the exploration noise's variance, gives the entropy (averaged over the states), and
        the standard deviation of the flow's actions, averaged over action dimensions and states, the spread
        (0 = a deterministic flow).
        """
        features = features[:n_states].repeat_interleave(n_samples, dim=0)
        actions = self.actor.sample(features, self.actor.draw_noise(features))
        flow_variance = actions.view(-1, n_samples, self.actor.action_dim).var(dim=1)  # (n_states, action_dim)
        action_spread = flow_variance.sqrt().mean().item()
        variance = flow_variance + self.actor.exploration_std.pow(2)
        if not bool((variance > 0).all()):
            return -math.inf, action_spread
        entropy = 0.5 * (math.log(2 * math.pi * math.e) + variance.log()).sum(dim=1).mean().item()
        return entropy, action_spread


#: The values the paper gives (its Table "Training hyper-parameters" and ``N_l = 20``), for
#: ``DACERF(..., **PAPER_HYPERPARAMETERS)``: learning rate 1e-4, replay batch 512, RAD, tau 0.001, policy delay 3,
#: Langevin 20 x 0.03 at temperature 0.01, one sampling step, no added exploration noise, the paper's weight
#: ``λ_f = c · ReLU(Q(s, a*) - Q(s, a_B))`` (``"paper"``, ``c = flow_matching_coef = 1``: the paper gives no constant)
#: and its data regime, 200 transitions collected per gradient step (``train_freq=200`` with one environment; with
#: ``n_envs`` environments use ``sb3_dacerf.common.regime.steps_per_gradient_kwargs(200, n_envs)``). Not the paper's:
#: RAD's ``zeta=1e-16`` (the paper gives none; pytorch-rad's default) and plain MLP critics (the paper names none).
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
    normalize_gradient: bool = False,
) -> th.Tensor:
    """
    Algorithm 1 of the DACER-F paper (Langevin Optimize Action): move replay actions ``a_B`` towards samples of
    ``p(a|s) ∝ exp(Q(s, a) / α)`` with ``N_l`` steps ``a <- a + η ∇_a Q(s, a) + sqrt(2 η α) ξ``, ``ξ ~ N(0, I)``,
    each clipped to the action bounds [-1, 1].

    :param action_gradient: ``∇_a Q(s, a)`` of a batch of actions ``(batch, action_dim)``, the states bound inside it
        (:class:`~sb3_dacerf.dacerf.policies.MinQActionGradient` for DACERF's critics)
    :param actions: The starting actions ``a_B``, in [-1, 1]
    :param n_steps: ``N_l``
    :param step_size: ``η``
    :param temperature: ``α``
    :param normalize_gradient: Divide ``∇_a Q`` by ``max(1, mean |∇_a Q|)`` over the batch at every step, so that a
        step moves a coordinate by ``η`` on average at most, whatever the reward's scale
    :return: The optimised actions ``a*``, detached
    """
    # ξ of every step, drawn at once and scaled by sqrt(2 η α)
    noise = th.randn((n_steps, *actions.shape), device=actions.device, dtype=actions.dtype).mul_(
        (2.0 * step_size * temperature) ** 0.5
    )
    action = actions.detach()  # a <- a_B
    for step in range(n_steps):
        gradient = action_gradient(action)  # ∇_a Q(s, a)
        if normalize_gradient:
            gradient = gradient / gradient.abs().mean().clamp(min=1.0)
        action = (action + step_size * gradient + noise[step]).clamp(-1.0, 1.0)  # a <- a + η ∇_a Q + sqrt(2ηα) ξ
    return action.detach()


def flow_matching_loss(
    velocity: Callable[[th.Tensor, th.Tensor], th.Tensor],
    targets: th.Tensor,
    noise: th.Tensor | None = None,
    time: th.Tensor | None = None,
) -> th.Tensor:
    """
    Conditional flow matching towards ``targets`` on the straight path ``a_t = (1 - t) a_0 + t a*``, whose
    velocity is ``a* - a_0``: the per-sample error ``||v(a_t, t) - (a* - a_0)||²``.

    :param velocity: Maps points ``a_t`` ``(batch, action_dim)`` and times ``t`` ``(batch, 1)`` to the predicted
        velocity ``v(s, a_t, t)``, the states bound inside it
    :param targets: The target actions ``a*``, ``(batch, action_dim)``
    :param noise: The path's starting points ``a_0``; ``N(0, I)`` draws by default
    :param time: The times ``t``; ``U[0, 1]`` draws by default
    :return: The squared error of each sample, ``(batch, 1)``
    """
    noise = th.randn_like(targets) if noise is None else noise
    time = th.rand((targets.shape[0], 1), device=targets.device, dtype=targets.dtype) if time is None else time
    actions_t = (1 - time) * noise + time * targets
    return (velocity(actions_t, time) - (targets - noise)).pow(2).sum(dim=1, keepdim=True)


def actor_loss_weights(
    method: str, q_values_star: th.Tensor, q_values_buffer: th.Tensor, coef: float = 1.0
) -> tuple[th.Tensor, th.Tensor]:
    """
    Weights of the actor loss ``J_F = mean(-Q(s, π(s)) / κ + λ_f ||v - (a* - a_0)||²)``: the scale ``κ`` of the
    improvement term and the per-sample weight ``λ_f`` of the flow-matching (imitation) term. Both keep the paper's
    ``λ_f ∝ g = ReLU(Q(s, a*) - Q(s, a_B))``, the Langevin gain of each sample:

    - ``"gain"``: ``κ = mean(g)`` and ``λ_f = coef · g / mean(g)``. Both terms are then free of the reward's scale
      and shift (``-Q / κ`` has the gradient of ``Q`` in units of the batch's Langevin gain). ``κ`` is floored at
      ``1e-3`` of the batch's mean absolute deviation of ``Q(s, a_B)`` for batches where Langevin dynamics found no
      gain.
    - ``"paper"``: ``κ = 1`` and ``λ_f = coef · g``, the paper's weight taken literally (the proportionality constant,
      which the paper does not give, is ``coef``).

    :param method: One of :data:`FLOW_MATCHING_WEIGHTS`
    :param q_values_star: ``Q(s, a*)`` of the Langevin targets, ``(batch, 1)``
    :param q_values_buffer: ``Q(s, a_B)`` of the replay actions the targets started from, ``(batch, 1)``
    :param coef: ``flow_matching_coef``, the weight of the imitation term
    :return: ``κ`` (a scalar tensor) and ``λ_f`` ``(batch, 1)``, both detached
    """
    with th.no_grad():
        gain = F.relu(q_values_star - q_values_buffer)
        mean_gain = gain.mean()
        if method == "gain":
            q_spread = (q_values_buffer - q_values_buffer.mean()).abs().mean()
            kappa = th.maximum(mean_gain, 1e-3 * q_spread).clamp_min(1e-8)
            return kappa, coef * (gain / mean_gain.clamp_min(1e-12))
        if method == "paper":
            return th.ones_like(mean_gain), coef * gain
    raise ValueError(f"Unknown flow_matching_weights={method!r}: it must be one of {', '.join(FLOW_MATCHING_WEIGHTS)}.")
