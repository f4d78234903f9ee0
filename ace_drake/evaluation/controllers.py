"""The rally controllers the product's command line can name: ``still``, ``returner`` (the
default: the model-based returner, ``control.returner``) and ``policy:<name>`` (a shipped policy
of ``models/policies/``). The returner's variants that exist for the studies of
docs/experiments/ (``returner:memoryless``, ``returner:forget=...``, ``returner:hit_state``,
``returner:hit_memory``) are named in ``analysis.experiments``.

Every controller has a policy's interface (a callable observation -> action (16,) | None, or a
torch module), so that the PolicyController runs any of them in the same rally diagram. A policy
whose actor outputs hit states (``sac.SacConfig.action``) plays through ``HitStatePolicy``.
"""

from __future__ import annotations

import dataclasses
import json
import warnings

import numpy as np

from ace_drake import artefacts
from ace_drake.config import MODELS_DIR, ConfigError
from ace_drake.contracts import DEFAULT_CONTROLLER, ObservationLayout  # noqa: F401 (DEFAULT_CONTROLLER: named here too)
from ace_drake.control.hit_state import HitStateLayer, PlannedHitState
from ace_drake.control.params import RallyParams
from ace_drake.control.returner import ModelBasedReturner
from ace_drake.evaluation.heldout import choose_controller, heldout_evaluations
from ace_drake.learning.networks import DeterministicPolicy
from ace_drake.learning.sac import load_policy
from ace_drake.perception.params import PerceptionParams
from ace_drake.physics.params import load_ball_params
from ace_drake.robot.model import scenario_file_record
from ace_drake.robot.params import scenario_mismatch
from ace_drake.systems.policy_controller import as_policy

POLICIES_DIR = MODELS_DIR / "policies"


def still(observation):
    """A controller that never moves the robot (the supervisor holds its reset pose): a baseline."""
    return None


class NoisyActions:
    """A controller whose every action gets independent Gaussian noise of standard deviation
    ``sigma`` per component (action units), clipped into the box; None stays None. How precise a
    controller's actions must be (docs/experiments/2026-12-01-imitation.md): a learned actor's imitation error is such a
    noise, though not an independent one. Seeded: by ``seed`` alone until an episode's start
    (``reset(seed)``, from the PolicyController's random context) reseeds it with [seed, the
    episode's seed], so that an episode's noise does not depend on the episodes before it;
    ``reset`` also restarts the wrapped controller's memory."""

    def __init__(self, controller, sigma: float, seed: int = 0):
        if not sigma >= 0.0:
            raise ConfigError(f"action noise must be >= 0, got {sigma}")

        self.controller, self._call, self.sigma, self.seed = controller, as_policy(controller), sigma, seed
        self.rng = np.random.default_rng(seed)

    def reset(self, seed: int | None = None) -> None:
        if seed is not None:
            self.rng = np.random.default_rng([self.seed, seed])
        reset = getattr(self.controller, "reset", None)
        if callable(reset):
            reset()

    def __call__(self, observation):
        action = self._call(observation)
        if action is None:
            return None
        return np.clip(np.asarray(action, dtype=float) + self.rng.normal(0.0, self.sigma, np.shape(action)), -1.0, 1.0)


class HitStatePolicy:
    """A hit-state policy (``DeterministicPolicy`` with action "hit_state") behind the fixed layer
    that makes its output an eq. (12) action (``control.hit_state.HitStateLayer``):
    ``controller(observation) -> action (16,) | None``. A policy trained with other command limits
    than the diagram's plays in its own hit-state coordinates (``HitStateLayer.with_parameterisation``)
    within the diagram's limits."""

    def __init__(self, policy, layer):
        if policy.hit_state is not None and not layer.parameterisation.matches(policy.hit_state):
            # Trained with other command limits: its actions are read in its own coordinates.
            layer = layer.with_parameterisation(policy.hit_state)
        self.policy, self.layer, self._call = policy, layer, as_policy(policy)

    @property
    def hit_memory(self) -> bool:
        """Whether the policy reads an observation that keeps its predicted hit."""
        return self.policy.hit_memory

    def __call__(self, observation):
        return self.layer(observation, self._call(observation))


def hit_state_controller(controller, params: RallyParams):
    """``controller`` ready for the rally diagram of ``params``: a hit-state DeterministicPolicy
    wrapped in ``HitStatePolicy`` with the layer it was trained for (meeting the ball or not;
    raises ConfigError if ``params`` does not compute the observation's hit prediction, which it
    needs: ``HitStateLayer.for_rally``), anything else unchanged."""

    if isinstance(controller, DeterministicPolicy) and controller.action == "hit_state":
        return HitStatePolicy(controller, HitStateLayer.for_rally(params, meet_ball=controller.meet_ball))
    return controller


def controller_names() -> list[str]:
    """The names ``make_controller`` accepts, shipped policies included."""
    policies = sorted(path.stem for path in POLICIES_DIR.glob("*.pt")) if POLICIES_DIR.is_dir() else []
    return ["still", "returner", *(f"policy:{name}" for name in policies)]


def make_controller(name: str, params: RallyParams):
    """The controller called ``name`` for the rally diagram of ``params``. Raises ConfigError
    naming the choices for an unknown name."""
    if name == "still":
        return still
    if name == "returner":
        return ModelBasedReturner.for_rally(params)
    if name.startswith("policy:"):
        path = POLICIES_DIR / f"{name.removeprefix('policy:')}.pt"
        if not path.is_file():
            raise ConfigError(f"no shipped policy {path.name} in {POLICIES_DIR}; choose one of {', '.join(controller_names())}")

        policy = load_policy(path)
        _warn_if_trained_for_another_robot(name, path, params)
        if policy.index.numel() and int(policy.index.max()) >= _observation_size(params):
            raise ConfigError(f"policy {name} reads a longer observation than the rally diagram of these params builds")
        if reads_hit_prediction(policy, params) and not params.hit_prediction:
            raise ConfigError(f"policy {name} reads the observation's hit_prediction part: build its diagram with RallyParams.hit_prediction true")
        return hit_state_controller(policy, params)
    raise ConfigError(f"unknown controller {name!r}; choose one of {', '.join(controller_names())}")


def best_controller(directory=None) -> tuple[str, float | None]:
    """The main job's controller and its held-out return rate (``evaluation.heldout``): of the
    controllers this checkout can build (``controller_names``), the best measured on the held-out
    players (the stored evaluations in ``directory``, default ``heldout.HELDOUT_DIR``)."""
    return choose_controller(heldout_evaluations(directory), controller_names())


def _warn_if_trained_for_another_robot(name: str, path, params: RallyParams) -> None:
    """A warning when the policy's sidecar records another robot than the diagram's (its states
    and actions are that robot's); sidecars written before the record existed say nothing."""
    sidecar = artefacts.sidecar_path(path)
    recorded = json.loads(sidecar.read_text()).get("robot") if sidecar.is_file() else None
    mismatch = None if recorded is None else scenario_mismatch(recorded, scenario_file_record(params.scenario))
    if mismatch:
        warnings.warn(f"policy {name} was trained for another robot ({mismatch}); it plays on this one as it is", stacklevel=3)


def _observation_size(params: RallyParams) -> int:
    return ObservationLayout(params.position_history, params.spin_history).size


def diagram_params_for(controller, params: RallyParams) -> RallyParams:
    """``params`` for the rally diagram of ``controller`` (possibly inside ``NoisyActions``):
    the observation's hit prediction (``RallyParams.hit_prediction``) off for the controllers
    known not to read it: ``still``, the returners (which predict the ball themselves) and loaded
    policies (``sac.load_policy``, ``SacLearner.policy``) whose actor does not read the part
    (a hit-state policy always does); its memory (``RallyParams.hit_memory``) on exactly for the
    controllers made for it (a hit-state policy or ``PlannedHitState`` with ``hit_memory``).
    Their observation then has zeros there: the same episodes, simulated ~1.4 x faster on the
    statistical path (``ace-drake bench sim``; a returner's own planning dominates its
    evaluation, ~1.1 x faster, docs/experiments/2026-11-30-speed.md). Any other callable keeps ``params`` as given."""


    inner = controller.controller if isinstance(controller, NoisyActions) else controller

    if inner is still or isinstance(inner, ModelBasedReturner):
        reads, memory = False, False
    elif isinstance(inner, (HitStatePolicy, PlannedHitState)):
        reads, memory = True, inner.hit_memory
    elif isinstance(inner, DeterministicPolicy):
        reads, memory = reads_hit_prediction(inner, params), inner.hit_memory
    else:
        return params
    reads = params.hit_prediction and reads
    return dataclasses.replace(params, hit_prediction=reads, hit_memory=reads and memory)


def reads_hit_prediction(policy, params: RallyParams) -> bool:
    """Whether a loaded policy (``sac.load_policy``) reads the ``hit_prediction`` part of the
    observation of ``params``' rally diagram."""

    part = ObservationLayout(params.position_history, params.spin_history).indices(["hit_prediction"])
    return bool(np.isin(policy.index.numpy(), part).any())


def rally_params(ball_params=None, sensors: str = "cameras", seed: int = 0, stepping: str = "continuous") -> RallyParams:
    """The rally diagram's config of the command line's options: the ball model of the YAML
    ``ball_params`` (None: the paper's), ball positions from ``sensors`` ("cameras" or
    "statistical"), ``seed``, and the diagram's ``stepping`` ("continuous", the reference, or
    "segment", the batched diagram)."""
    return RallyParams(physics=load_ball_params(ball_params), perception=PerceptionParams(positions=sensors), seed=seed, stepping=stepping)
