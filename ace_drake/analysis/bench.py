"""Benchmarks: speed measured side by side in one run, reported as medians and ratios."""

from __future__ import annotations

import time
from typing import Callable

import numpy as np

from ace_drake.diagrams import build_ball_diagram, make_simulator
from ace_drake.physics.flight import make_state
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import simulate


def _median_seconds(run: Callable[[], None], repeats: int) -> tuple[float, float]:
    """Median and p99 (s) of ``repeats`` timed calls of ``run``, after one warm-up call."""
    run()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        samples.append(time.perf_counter() - start)
    return float(np.median(samples)), float(np.percentile(samples, 99))


def sample_incoming_balls(n: int, seed: int = 0) -> np.ndarray:
    """(n, 9) plausible shots from the human side towards the robot (x from 1.2 to 1.8 m)."""
    rng = np.random.default_rng(seed)
    return make_state(
        np.c_[rng.uniform(1.2, 1.8, n), rng.uniform(-0.5, 0.5, n), rng.uniform(0.1, 0.35, n)],
        np.c_[rng.uniform(-12.0, -5.0, n), rng.uniform(-1.0, 1.0, n), rng.uniform(0.0, 2.5, n)],
        rng.normal(0.0, 200.0, (n, 3)),
    )


def ball_plant_runner(params: BallPhysicsParams | None = None, log_period: float = 0.0) -> Callable[[np.ndarray, float], None]:
    """The BallPlant in one Simulator (``build_ball_diagram``, logging every ``log_period`` s, 0:
    every step): returns run(shot, seconds), which starts the ball at ``shot`` (9,) at t = 0 and
    simulates ``seconds`` s."""
    diagram = build_ball_diagram(params, log_period=log_period)
    ball = diagram.GetSubsystemByName("ball")
    simulator = make_simulator(diagram)
    context = simulator.get_mutable_context()

    def run(shot: np.ndarray, seconds: float) -> None:
        context.SetTime(0.0)
        ball.SetBallState(ball.GetMyMutableContextFromRoot(context), shot)
        simulator.Initialize()
        simulator.AdvanceTo(seconds)

    return run


def bench_ball(repeats: int = 5, seconds: float = 1.0, batch: int = 1000, progress=None) -> dict:
    """Simulated ball-seconds per wall-second: the RK4 propagator for one ball and for a batch,
    and the BallPlant in a Simulator, each over ``seconds`` of simulated time with contacts."""
    params = BallPhysicsParams()
    say = progress or (lambda _: None)
    single = sample_incoming_balls(1)
    balls = sample_incoming_balls(batch)

    say("propagator, 1 ball")
    one_median, one_p99 = _median_seconds(lambda: simulate(single, params, seconds, record=False), repeats)
    say(f"propagator, {batch} balls")
    many_median, many_p99 = _median_seconds(lambda: simulate(balls, params, seconds, record=False), max(1, repeats // 2))

    run_plant = ball_plant_runner(params)
    say("BallPlant in a Simulator, 1 ball")
    plant_median, plant_p99 = _median_seconds(lambda: run_plant(single[0], seconds), repeats)
    rates = {
        "propagator_1_ball": seconds / one_median,
        f"propagator_{batch}_balls": batch * seconds / many_median,
        "ball_plant_simulator": seconds / plant_median,
    }
    return {
        "benchmark": "ball",
        "simulated_seconds_per_run": seconds,
        "repeats": repeats,
        "ball_seconds_per_wall_second": rates,
        "wall_seconds_median": {
            "propagator_1_ball": one_median,
            f"propagator_{batch}_balls": many_median,
            "ball_plant_simulator": plant_median,
        },
        "wall_seconds_p99": {
            "propagator_1_ball": one_p99,
            f"propagator_{batch}_balls": many_p99,
            "ball_plant_simulator": plant_p99,
        },
        "ratios": {
            "batched_over_single_propagator": rates[f"propagator_{batch}_balls"] / rates["propagator_1_ball"],
            "ball_plant_over_single_propagator": rates["ball_plant_simulator"] / rates["propagator_1_ball"],
        },
    }
