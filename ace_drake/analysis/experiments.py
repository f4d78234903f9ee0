"""Controllers that exist for the studies of docs/experiments/, not for the product.

The product's command line names ``still``, ``returner`` and ``policy:<name>``
(``evaluation.controllers``). The studies compared the returner with variants of it; they are named
here, for those studies and their tests, and run through the same rally diagram
(``evaluation.evaluate.evaluate``, ``evaluation.controllers.diagram_params_for``):

- ``returner:memoryless``: ``ReturnerParams.memory`` off, every action a function of the
  observation alone (docs/experiments/2026-12-01-returner-memory.md). The kept hit-state training
  configs label with this returner (their ``returner: {memory: false}``), as a config value, not
  a controller name.
- ``returner:forget=<part>[+<part>...]``: the returner with memory, the named parts of it forgotten
  (``ReturnerParams.forget``, ``control.params.RETURNER_MEMORY_PARTS``; the same note).
- ``returner:hit_state``: the memoryless returner's planned hit states played through the
  hit-state layer (``control.hit_state.PlannedHitState``): the layer's ceiling, what an actor that
  imitated its labeller perfectly would return (docs/experiments/2026-12-01-hit-state-actor.md).
- ``returner:hit_memory``: the same on an observation that keeps its predicted hit
  (``RallyParams.hit_memory``): the labeller of the shipped hit-state policies.

For example::

    params = RallyParams()
    controller = make_controller("returner:memoryless", params)
    figures = evaluate(controller, params, shots, serve, seed=0)
"""

from __future__ import annotations

from ace_drake.config import ConfigError
from ace_drake.control.hit_state import HitStateLayer, PlannedHitState
from ace_drake.control.params import RallyParams, ReturnerParams
from ace_drake.control.returner import ModelBasedReturner
from ace_drake.evaluation import controllers

STUDY_CONTROLLERS = ("returner:memoryless", "returner:forget=<part>[+<part>...]", "returner:hit_state", "returner:hit_memory")


def controller_names() -> list[str]:
    """The names ``make_controller`` accepts: the product's and the studies'."""
    return [*controllers.controller_names(), *STUDY_CONTROLLERS]


def make_controller(name: str, params: RallyParams):
    """The controller called ``name`` (a study's or the product's) for the rally diagram of
    ``params``. Raises ConfigError naming the choices for an unknown name."""
    if name == "returner:memoryless":
        return ModelBasedReturner.for_rally(params, ReturnerParams(memory=False))
    if name.startswith("returner:forget="):
        return ModelBasedReturner.for_rally(params, ReturnerParams(forget=tuple(name.removeprefix("returner:forget=").split("+"))))
    if name in ("returner:hit_state", "returner:hit_memory"):
        return PlannedHitState(ModelBasedReturner.for_rally(params, ReturnerParams(memory=False)), HitStateLayer.for_rally(params),
                               hit_memory=name == "returner:hit_memory")
    if name.startswith("returner:"):
        raise ConfigError(f"unknown controller {name!r}; choose one of {', '.join(controller_names())}")
    return controllers.make_controller(name, params)
