"""The ball demo: one launch with topspin, no spin and backspin, simulated through the BallPlant.

Tutorial 01 runs it: every shot goes through the same Diagram and Simulator (the context is reset
between shots), the contacts come from the BallPlant's contact_events port, and an optional
Meshcat recording shows the three flights one after the other.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from pydrake.common import RandomGenerator
from pydrake.geometry import Meshcat

from ace_drake.diagrams import build_ball_diagram, make_simulator
from ace_drake.physics.flight import make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactEvent, ContactKind

# A drive from the robot's side: struck 1.6 m behind the net, 0.25 m above the table.
LAUNCH_POSITION = (-1.6, -0.2, 0.25)  # m
LAUNCH_VELOCITY = (5.5, 0.5, 2.0)  # m/s; all three spins land on the far half
SPIN_RATE = 250.0  # rad/s, about the median spin of the recorded human shots


def spin_comparison_shots(spin_rate: float = SPIN_RATE) -> dict[str, np.ndarray]:
    """The same launch with topspin (+w_y for a ball moving +x), no spin and backspin, (9,) each."""
    return {
        name: make_state(LAUNCH_POSITION, LAUNCH_VELOCITY, [0.0, sign * spin_rate, 0.0])
        for name, sign in [("topspin", 1.0), ("no spin", 0.0), ("backspin", -1.0)]
    }


@dataclasses.dataclass
class ShotResult:
    """A simulated shot: its name, the sampled times (s) and states (T, 9), and its contacts."""

    name: str
    times: np.ndarray
    states: np.ndarray
    events: tuple[ContactEvent, ...]

    def first(self, kind: ContactKind) -> ContactEvent | None:
        """The first contact of ``kind``, or None."""
        return next((e for e in self.events if e.kind == kind), None)


def run_shots(
    shots: dict[str, np.ndarray],
    params: BallPhysicsParams | None = None,
    duration: float = 1.2,
    meshcat: Meshcat | None = None,
    seed: int = 0,
    perturb: bool = False,
) -> list[ShotResult]:
    """Simulates each shot for ``duration`` seconds in one ball diagram, one after the other.

    With ``meshcat``, the shots are recorded back to back (shot i plays from i * duration) and the
    recording is published; ``meshcat.StaticHtml()`` then gives a self-contained replay.
    """
    if duration <= 0:
        raise ValueError(f"run_shots: duration must be > 0 s, got {duration}")
    params = params or BallPhysicsParams()
    diagram = build_ball_diagram(params, meshcat=meshcat, perturb=perturb, seed=seed, log_period=0.005)
    ball = diagram.GetSubsystemByName("ball")
    logger = diagram.GetSubsystemByName("ball_logger")
    simulator = make_simulator(diagram)
    context = simulator.get_mutable_context()
    if meshcat is not None:
        meshcat.StartRecording(frames_per_second=100.0, set_visualizations_while_recording=False)
    results = []
    for index, (name, state) in enumerate(shots.items()):
        start = index * duration
        context.SetTime(start)
        diagram.SetRandomContext(context, RandomGenerator(seed + index))  # the perturbations' seed
        ball_context = ball.GetMyMutableContextFromRoot(context)
        ball.SetBallState(ball_context, state)
        log = logger.GetMutableLog(logger.GetMyContextFromRoot(context))
        log.Clear()
        simulator.Initialize()
        simulator.AdvanceTo(start + duration)
        events = ball.contact_events_port.Eval(ball_context)
        results.append(ShotResult(name, log.sample_times() - start, log.data().T.copy(), tuple(
            dataclasses.replace(e, time=e.time - start) for e in events
        )))
    if meshcat is not None:
        meshcat.StopRecording()
        meshcat.PublishRecording()
    return results


def summarize_shots(results: list[ShotResult], params: BallPhysicsParams | None = None) -> list[dict]:
    """Per shot: net clearance (m), first bounce position (m), time (s), speed and spin after it."""
    net_height = (params or BallPhysicsParams()).net.height
    rows = []
    for result in results:
        crossing = np.flatnonzero(np.diff(np.sign(result.states[:, 0])) > 0)
        net_clearance = None
        if crossing.size:
            i = crossing[0]
            fraction = -result.states[i, 0] / (result.states[i + 1, 0] - result.states[i, 0])
            height = result.states[i, 2] + fraction * (result.states[i + 1, 2] - result.states[i, 2])
            net_clearance = float(height - net_height)
        bounce = result.first(ContactKind.TABLE)
        row = {
            "shot": result.name,
            "contacts": [e.kind.name.lower() for e in result.events],
            "net_clearance_m": net_clearance,
        }
        if bounce is not None:
            row.update(
                bounce_time_s=float(bounce.time),
                bounce_position_m=[float(v) for v in bounce.state_pre[:2]],
                speed_after_bounce_mps=float(np.linalg.norm(bounce.state_post[3:6])),
                spin_after_bounce_radps=[float(v) for v in bounce.state_post[6:9]],
            )
        rows.append(row)
    return rows
