"""
DeepMind Control suite tasks as Gymnasium environments with a flat ``float32`` observation and a ``[-1, 1]`` action
box: every state-based task of ``dm_control.suite`` is registered as ``DMC-<domain>-<task>-v0`` (dm-control's names,
e.g. ``DMC-humanoid-stand-v0``), beside shimmy's ``dm_control/<domain>-<task>-v0`` ids (a ``Dict`` of ``float64``).
Registration imports no simulator. An env made without a ``render_mode`` loads no OpenGL backend (without a display,
dm-control's GLFW would print its ``DISPLAY`` error); the first env that renders loads the one dm-control would
choose. The two ``lqr`` tasks are left out: their actuators are unbounded and their episodes have no time limit.
"""

import logging
import os
import re
import sys
from types import ModuleType
from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np
from gymnasium import spaces

# dm_control.suite.ALL_TASKS without ``lqr`` (tests/test_dmc.py checks it against the installed dm-control)
_SUITE = {
    "acrobot": "swingup swingup_sparse",
    "ball_in_cup": "catch",
    "cartpole": "balance balance_sparse swingup swingup_sparse two_poles three_poles",
    "cheetah": "run",
    "dog": "stand walk trot run fetch",
    "finger": "spin turn_easy turn_hard",
    "fish": "upright swim",
    "hopper": "stand hop",
    "humanoid": "stand walk run run_pure_state",
    "humanoid_CMU": "stand walk run",
    "manipulator": "bring_ball bring_peg insert_ball insert_peg",
    "pendulum": "swingup",
    "point_mass": "easy hard",
    "quadruped": "walk run escape fetch",
    "reacher": "easy hard",
    "stacker": "stack_2 stack_4",
    "swimmer": "swimmer6 swimmer15",
    "walker": "stand walk run",
}
DMC_TASKS: tuple[tuple[str, str], ...] = tuple((domain, task) for domain, tasks in _SUITE.items() for task in tasks.split())
DMC_ENV_IDS: tuple[str, ...] = tuple(f"DMC-{domain}-{task}-v0" for domain, task in DMC_TASKS)
DMC_EPISODE_STEPS = 1000
"""Every registered task's episodes end after 1000 control steps."""
# Tasks whose reset uploads a new terrain to OpenGL, so they need a GL backend even without rendering
_TASKS_NEEDING_GL = frozenset({("quadruped", "escape")})
_renderer_deferred = False  # whether this module kept dm-control from loading a backend


def _no_gl_error(what: str) -> RuntimeError:
    return RuntimeError(
        f"{what}, but MuJoCo has no working OpenGL backend (MUJOCO_GL={os.environ.get('MUJOCO_GL', '<unset>')}). "
        "Without a display, set MUJOCO_GL=egl (GPU or Mesa EGL) or MUJOCO_GL=osmesa (CPU) before Python starts."
    )


def _dm_control_suite(rendering: bool) -> ModuleType:
    """
    ``dm_control.suite``, imported without an OpenGL backend unless ``rendering`` (or ``MUJOCO_GL``) asks for one;
    once an env renders, the backend dm-control would have chosen (``MUJOCO_GL``, else the first of GLFW, EGL and
    OSMesa that loads) is loaded.
    """
    global _renderer_deferred
    import mujoco  # noqa: F401  (MuJoCo reads MUJOCO_GL for its own renderer when imported: before the change below)

    if not rendering and "MUJOCO_GL" not in os.environ and "dm_control._render" not in sys.modules:
        os.environ["MUJOCO_GL"] = "off"  # dm-control's name for no renderer, read once, at its first import
        try:
            import dm_control._render  # noqa: F401
        finally:
            del os.environ["MUJOCO_GL"]
        _renderer_deferred = True
    from dm_control import _render, suite

    if rendering and _renderer_deferred:
        wanted = os.environ.get("MUJOCO_GL")
        for names, import_renderer in _render._ALL_RENDERERS:  # as dm-control's import does
            if wanted is not None and wanted not in names:
                continue
            try:
                _render.Renderer = import_renderer()
            except ImportError:
                continue
            _render.BACKEND = names[0]
            _render.USING_GPU = _render.BACKEND in _render.constants.EGL + _render.constants.GLFW
            break
        _renderer_deferred = False
    return suite


# MuJoCo warns, through absl, of attributes of dm-control's own model files (cheetah's settotalmass): not the user's
_MODEL_FILE_DEPRECATION = re.compile(r"compiler attribute '\w+' is deprecated")


def _no_model_file_deprecation(record: logging.LogRecord) -> bool:
    return not _MODEL_FILE_DEPRECATION.search(record.getMessage())


class DMCEnv(gym.Wrapper[np.ndarray, np.ndarray, dict[str, np.ndarray], np.ndarray]):
    """
    A ``dm_control.suite`` task (``domain_name``, ``task_name``) through shimmy, its observation dict flattened to one
    ``float32`` vector (in the task's order) and its action box mapped to ``[-1, 1]``; ``reset(seed=...)`` seeds the
    initial state; ``env.unwrapped`` is shimmy's ``DmControlCompatibilityV0``. ``render_mode="rgb_array"`` needs a
    MuJoCo OpenGL backend (without a display, ``MUJOCO_GL=egl`` or ``osmesa``), ``"human"`` a display;
    ``render_kwargs`` go to ``physics.render``, ``task_kwargs`` and ``environment_kwargs`` to ``dm_control.suite.load``.
    """

    metadata: dict[str, Any] = {"render_modes": ["rgb_array", "human"], "render_fps": 50}  # noqa: RUF012  (gymnasium.Env declares it without ClassVar)

    def __init__(
        self,
        domain_name: str,
        task_name: str,
        render_mode: str | None = None,
        render_kwargs: dict[str, Any] | None = None,
        task_kwargs: dict[str, Any] | None = None,
        environment_kwargs: dict[str, Any] | None = None,
    ) -> None:
        needs_gl = (domain_name, task_name) in _TASKS_NEEDING_GL
        suite = _dm_control_suite(rendering=render_mode is not None or needs_gl)
        from shimmy.dm_control_compatibility import DmControlCompatibilityV0

        absl = logging.getLogger("absl")
        absl.addFilter(_no_model_file_deprecation)
        try:
            dm_env = suite.load(domain_name, task_name, task_kwargs=task_kwargs, environment_kwargs=environment_kwargs)
        finally:
            absl.removeFilter(_no_model_file_deprecation)
        if needs_gl:
            try:
                _ = dm_env.physics.contexts  # creating the GL context is what fails without a backend
            # MuJoCo reports a missing OpenGL backend with several exception types (FatalError, RuntimeError, ...)
            except Exception as error:
                raise _no_gl_error(f"{domain_name}-{task_name} needs OpenGL at every reset") from error
        super().__init__(DmControlCompatibilityV0(dm_env, render_mode=render_mode, render_kwargs=render_kwargs))
        self.metadata = {**self.metadata, "render_fps": round(1.0 / dm_env.control_timestep())}
        # Keys in the task's own order (shimmy's Dict space sorts them)
        self._obs_keys = tuple(dm_env.observation_spec().keys())
        n_obs = sum(int(np.prod(spec.shape)) for spec in dm_env.observation_spec().values())
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(n_obs,), dtype=np.float32)
        action_spec = dm_env.action_spec()
        self._action_low = np.asarray(action_spec.minimum, dtype=np.float64)
        self._action_scale = (np.asarray(action_spec.maximum, dtype=np.float64) - self._action_low) / 2.0
        self.action_space = spaces.Box(-1.0, 1.0, shape=action_spec.shape, dtype=np.float32)

    def _flatten(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        return np.concatenate([np.asarray(obs[key], dtype=np.float32).ravel() for key in self._obs_keys])

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        obs, info = self.env.reset(seed=seed, options=options)
        # gymnasium types Wrapper.env with the wrapper's observation type, not the wrapped env's (a dict here)
        return self._flatten(obs), info  # type: ignore[arg-type]

    def step(self, action: np.ndarray) -> tuple[np.ndarray, SupportsFloat, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(self._action_low + (action + 1.0) * self._action_scale)
        return self._flatten(obs), float(reward), terminated, truncated, info  # type: ignore[arg-type]  # as in reset

    def render(self) -> Any:
        try:
            return self.env.render()
        # MuJoCo reports a missing OpenGL backend with several exception types (FatalError, AttributeError, ...)
        except Exception as error:
            raise _no_gl_error(f"render_mode={self.render_mode!r} was asked") from error


for (_domain, _task), _env_id in zip(DMC_TASKS, DMC_ENV_IDS, strict=True):
    gym.register(
        id=_env_id,
        entry_point="sb3_dacerf.envs.dmc:DMCEnv",
        max_episode_steps=DMC_EPISODE_STEPS,
        kwargs={"domain_name": _domain, "task_name": _task},
    )
