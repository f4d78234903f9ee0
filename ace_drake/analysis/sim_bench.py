"""``ace-drake bench sim``: how fast the closed-loop rally simulates, and where the time goes.

Measured side by side in one process on one core (issue 6 aims at >= 20 x real time):

- the real-time factor (simulated s per wall s) of the full rally diagram
  (``diagrams.build_rally_diagram``: ball, robot, perception, estimator, observation, control stack
  with collision checking, loggers) with (a) the nine analytic cameras and the triangulator and
  (b) the training path's statistical position sensor, and (c) the same without the observation's
  hit prediction (``RallyParams.hit_prediction`` off: what the prediction costs), under a
  ready-pose controller (every 32 ms the control stack steers towards the ready pose:
  ``ControlStack.action_towards``), over the same incoming shots; median over episodes of
  ``seconds`` simulated seconds each;
- the two ceilings any rally diagram runs below, since it contains both: the ball alone
  (``diagrams.build_ball_diagram``: the BallPlant in a Simulator, the same shots and seconds) and
  the robot alone under the same ready-pose controller through the whole control stack
  (``diagrams.build_controlled_robot_diagram``: the 1 kHz robot interface of DESIGN.md, the
  segment decisions with their collision checks; no ball, no perception);
- RallyEnv (the training diagram) environment steps per second with uniformly random actions,
  resets included, and how long its episodes last;
- a profile of one episode per sensor path attributing wall time to the diagram's systems: a
  ``sys.setprofile`` tracer charges the time between Python events to the innermost system
  callback running (a method of a LeafSystem in ``ace_drake/systems``; helpers such as the
  physics, EKF or control-stack code, or the systems' state classes, count for the system that
  called them); the rest is Drake's C++ (integrator, event dispatch, caches) and the benchmark's
  own code. Tracing slows Python more than C++, so the shares are indicative; the top functions
  by own time come from cProfile.

After each diagram is built, the garbage of building it is collected and the live objects are
frozen out of the collector's view (``_settle``: ``gc.freeze``; undone at the end): a full
collection over a built diagram's ~300k objects costs ~0.3 s, and without this it lands in
whichever timed episode happens to trigger it. The figures are the steady state.
"""

from __future__ import annotations

import cProfile
import dataclasses
import gc
import pstats
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ace_drake.analysis.bench import ball_plant_runner
from ace_drake.config import MODELS_DIR
from ace_drake.contracts import ObservationLayout
from ace_drake.control.action_mapping import ACTION_SIZE
from ace_drake.control.feasible_set import InfeasibleStartError
from ace_drake.control.params import RallyParams
from ace_drake.control.stack import ControlStack
from ace_drake.diagrams import (
    build_controlled_robot_diagram,
    build_rally_diagram,
    build_segment_rally_diagram,
    make_segment_simulator,
    make_simulator,
    start_controlled_robot,
    start_segment_episodes,
)
from ace_drake.evaluation.runner import RallyRunner
from ace_drake.perception.params import PerceptionParams
from ace_drake.play.params import ShotParams
from ace_drake.play.shots import make_distribution
from ace_drake.robot.model import load_scenario
from ace_drake.training.env import RallyEnv
from ace_drake.training.vector_env import RallyVectorEnv

SENSOR_PATHS = {"cameras": "analytic cameras + triangulator", "statistical": "statistical position sensor"}
# The rally rows: (key, position sensor, hit prediction on).
RALLY_CASES = (("cameras", "cameras", True), ("statistical", "statistical", True), ("statistical_no_hit_prediction", "statistical", False))
SYSTEMS_DIR = str(Path(__file__).resolve().parents[1] / "systems")
OUTSIDE_SYSTEMS = "(Drake C++ and non-system Python)"
LOG_PERIOD = 0.002  # s, the loggers' period in the ceilings' diagrams: build_rally_diagram's default


class ReadyPosePolicy:
    """A controller that always steers towards the ready (reset) pose through the control stack:
    a policy callable observation -> action for ``build_rally_diagram`` (``layout``: the rally's
    ObservationLayout) or for ``build_controlled_robot_diagram`` (``layout`` None: the observation
    is the robot state [q, v, a] itself)."""

    def __init__(self, stack, layout=None):
        self.stack, self.layout = stack, layout

    @staticmethod
    def for_rally(params: RallyParams, layout=None) -> "ReadyPosePolicy":
        """The controller over its own stack for the scenario and control of ``params`` (it needs
        the limits and mapping, not collision checks: the diagram's supervisor checks)."""

        return ReadyPosePolicy(ControlStack(load_scenario(MODELS_DIR / params.scenario), params.control), layout)

    def __call__(self, observation: np.ndarray) -> np.ndarray:
        robot_state = observation if self.layout is None else self.layout.part(observation, "robot_state")
        q, v, a = np.split(robot_state, 3)
        try:
            return self.stack.action_towards(q, v, a, self.stack.reset_pose)
        except InfeasibleStartError:  # on a reset outside the invariant set: nothing to ask
            return np.zeros(ACTION_SIZE)


@dataclasses.dataclass
class RallyBench:
    """A rally diagram under the ready-pose controller, and its runner (one Simulator)."""

    positions: str
    runner: object

    @staticmethod
    def build(positions: str, hit_prediction: bool = True) -> "RallyBench":
        params = RallyParams(perception=PerceptionParams(positions=positions), hit_prediction=hit_prediction)
        policy = ReadyPosePolicy.for_rally(params, ObservationLayout(params.position_history, params.spin_history))
        return RallyBench(positions, RallyRunner(build_rally_diagram(params, policy), params))

    def episode(self, shot: np.ndarray, seed: int, seconds: float) -> tuple[float, float]:
        """Simulates ``seconds`` from ``shot``; returns the wall and CPU (process) time of the
        simulation, s."""
        self.runner.reset(shot, seed=seed)
        wall, cpu = time.perf_counter(), time.process_time()
        self.runner.simulator.AdvanceTo(seconds)
        return time.perf_counter() - wall, time.process_time() - cpu


def _ceilings(shots: np.ndarray, seconds: float, say) -> dict:
    """The ball alone and the controlled robot alone (module docstring), each over ``seconds``
    simulated s per episode, one warm-up episode then one per remaining shot: simulated s per CPU
    s of this process, median."""

    def rate(run) -> float:
        cpu = time.process_time()
        run()
        return seconds / (time.process_time() - cpu)

    say("ceilings: the ball alone")
    run_ball = ball_plant_runner(log_period=LOG_PERIOD)
    ball_rates = [rate(lambda: run_ball(shot, seconds)) for shot in shots][1:]

    say("ceilings: the robot alone under the control stack")
    robot_diagram = build_controlled_robot_diagram(ReadyPosePolicy.for_rally(RallyParams()), log_period=LOG_PERIOD)
    robot_simulator = make_simulator(robot_diagram)
    robot_context = robot_simulator.get_mutable_context()
    _settle()

    def run_robot() -> None:
        robot_context.SetTime(0.0)
        start_controlled_robot(robot_diagram, robot_context)
        robot_simulator.Initialize()
        robot_simulator.AdvanceTo(seconds)

    robot_rates = [rate(run_robot) for _ in shots][1:]
    return {
        "ball_alone_cpu_real_time_factor_median": float(np.median(ball_rates)),
        "controlled_robot_alone_cpu_real_time_factor_median": float(np.median(robot_rates)),
    }


def bench_sim(seconds: float = 1.0, episodes: int = 5, env_episodes: int = 40, seed: int = 0, profile: bool = True,
              batches=(1, 16, 64, 256), vector_steps: int = 40, progress: Callable[[str], None] | None = None) -> dict:
    """The figures of the module docstring. ``seconds``: simulated s per rally episode;
    ``episodes``: timed rally episodes per sensor path (after one warm-up); ``env_episodes``:
    RallyEnv episodes with random actions (after one warm-up); ``batches``: the RallyVectorEnv
    sizes B measured, each for ``vector_steps`` steps (after a warm-up); ``profile``: add the
    per-system profile."""

    try:
        return _bench_sim(seconds, episodes, env_episodes, seed, profile, batches, vector_steps, progress)
    finally:
        gc.unfreeze()


def _bench_sim(seconds, episodes, env_episodes, seed, profile, batches, vector_steps, progress) -> dict:
    """``bench_sim``'s measurements (the heap frozen after each build: ``_settle``)."""
    say = progress or (lambda _: None)
    if seconds <= 0 or episodes < 1 or env_episodes < 1:
        raise ValueError(f"bench sim: seconds must be > 0 and episodes >= 1, got {seconds}, {episodes}, {env_episodes}")
    say("fitting the incoming-shot distribution (synthetic set)")
    distribution = make_distribution(ShotParams(seed=seed))
    shots = distribution.sample(np.random.default_rng(seed), episodes + 1)
    figures: dict = {"simulated_seconds_per_episode": seconds, "episodes": episodes, "controller": "ready pose (ControlStack.action_towards)"}
    benches = {}
    for key, positions, hit_prediction in RALLY_CASES:
        label = SENSOR_PATHS[positions] + ("" if hit_prediction else ", no hit prediction")
        say(f"rally diagram, {label}: building")
        bench = RallyBench.build(positions, hit_prediction)
        _settle()
        if hit_prediction:
            benches[positions] = bench
        walls, cpus = [], []
        for index, shot in enumerate(shots):
            wall, cpu = bench.episode(shot, seed + index, seconds)
            if index > 0:  # the first episode warms caches up
                walls.append(wall)
                cpus.append(cpu)
                say(f"  episode {index}: {seconds / wall:.2f} x real time ({seconds / cpu:.2f} per CPU second)")
        rtf = seconds / np.array(walls)
        figures[f"rally_{key}"] = {
            "sensors": label,
            "real_time_factor_median": float(np.median(rtf)),
            "real_time_factor_min": float(np.min(rtf)),
            # Simulated s per CPU s of this process: what the wall figure would be on an idle core.
            "cpu_real_time_factor_median": float(np.median(seconds / np.array(cpus))),
            "wall_seconds_median": float(np.median(walls)),
        }
    rate = {key: figures[f"rally_{key}"]["real_time_factor_median"] for key, _, _ in RALLY_CASES}
    figures["ratio_statistical_to_cameras"] = rate["statistical"] / rate["cameras"]
    figures["ratio_no_hit_prediction_to_statistical"] = rate["statistical_no_hit_prediction"] / rate["statistical"]

    figures["ceilings"] = _ceilings(shots, seconds, say)

    say("RallyEnv (training diagram, statistical sensors), random actions")
    env = RallyEnv(distribution=distribution)
    _settle()
    figures["env"] = _bench_env(env, env_episodes, seed, say)

    for positions in ("cameras", "statistical"):
        say(f"segment-stepped rally diagram, B = 1, {SENSOR_PATHS[positions]}")
        figures[f"rally_{positions}_b1"] = _segment_rally(positions, shots, seconds, seed, say)
    figures["ratio_cameras_b1_new_to_old"] = figures["rally_cameras_b1"]["real_time_factor_median"] / figures["rally_cameras"]["real_time_factor_median"]
    figures["segment_env"] = {}
    for batch in batches:
        say(f"RallyVectorEnv, B = {batch}, random actions")
        figures["segment_env"][str(batch)] = _bench_vector_env(batch, vector_steps, seed, distribution, say)
    best = max(figures["segment_env"].values(), key=lambda entry: entry["steps_per_second"])
    figures["ratio_env_steps_new_to_old"] = best["steps_per_second"] / figures["env"]["steps_per_second"]

    if profile:
        figures["profile"] = {}
        for positions, bench in benches.items():
            say(f"profiling one rally episode, {SENSOR_PATHS[positions]}")
            figures["profile"][positions] = profile_by_system(lambda: bench.episode(shots[0], seed, seconds), seconds)
        say("profiling RallyEnv episodes with random actions")
        rng = np.random.default_rng(seed)
        figures["profile"]["env"] = profile_by_system(lambda: [_env_episode(env, rng, None) for _ in range(3)], None)
        batch = 64 if 64 in batches else max(batches)
        say(f"profiling RallyVectorEnv steps, B = {batch}")
        vector = RallyVectorEnv(batch, distribution=distribution)
        vector.reset(seed=seed)
        figures["profile"][f"segment_env_b{batch}"] = profile_by_system(
            lambda: [vector.step(rng.uniform(-1.0, 1.0, (batch, ACTION_SIZE))) for _ in range(10)], None)
    return figures


def _segment_rally(positions: str, shots: np.ndarray, seconds: float, seed: int, say) -> dict:
    """The ready-pose rally of ``RallyBench`` on the segment-stepped diagram (B = 1): real-time
    factors over the same shots (the first a warm-up)."""
    params = RallyParams(perception=PerceptionParams(positions=positions), stepping="segment")
    policy = ReadyPosePolicy.for_rally(params, ObservationLayout(params.position_history, params.spin_history))
    diagram = build_segment_rally_diagram(params, policy, 1)
    simulator = make_segment_simulator(diagram)
    context, default = simulator.get_mutable_context(), diagram.CreateDefaultContext()
    _settle()
    ticks = int(np.ceil(seconds / params.control.segment_samples / 1e-3))
    walls = []
    for index, shot in enumerate(shots):
        context.SetTimeStateAndParametersFrom(default)
        start_segment_episodes(diagram, context, [0], shot[None], [seed + index])
        diagram.GetInputPort("light_curtain").FixValue(context, np.zeros(1))
        simulator.Initialize()
        start = time.perf_counter()
        simulator.AdvanceTo(ticks * params.control.segment_samples * 1e-3)
        if index > 0:
            walls.append(time.perf_counter() - start)
            say(f"  episode {index}: {ticks * 0.032 / walls[-1]:.1f} x real time")
    rtf = ticks * params.control.segment_samples * 1e-3 / np.array(walls)
    return {"sensors": SENSOR_PATHS[positions], "real_time_factor_median": float(np.median(rtf)), "real_time_factor_min": float(np.min(rtf))}


def _bench_vector_env(batch: int, steps: int, seed: int, distribution, say) -> dict:
    """RallyVectorEnv of B = ``batch`` with random actions: steps per second (B per step) after a
    warm-up of a few steps, and the process's resident memory after it."""
    env = RallyVectorEnv(batch, distribution=distribution)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    _settle()
    for _ in range(3):
        env.step(rng.uniform(-1.0, 1.0, (batch, ACTION_SIZE)))
    start, cpu = time.perf_counter(), time.process_time()
    ends = 0
    for _ in range(steps):
        _, _, terminated, _, _ = env.step(rng.uniform(-1.0, 1.0, (batch, ACTION_SIZE)))
        ends += int(terminated.sum())
    wall = time.perf_counter() - start
    figures = {"steps_per_second": steps * batch / wall, "steps_per_cpu_second": steps * batch / (time.process_time() - cpu),
               "episodes_ended": ends, "resident_memory_mb": resident_memory_mb()}
    say(f"  B = {batch}: {figures['steps_per_second']:.0f} steps/s, {figures['resident_memory_mb']:.0f} MB resident")
    return figures


def _settle() -> None:
    """Collects the garbage of a build and freezes the live objects out of the collector's view
    (module docstring); ``bench_sim`` unfreezes them at the end."""
    gc.collect()
    gc.freeze()


def resident_memory_mb() -> float:
    """This process's resident memory now, MB (Linux /proc; NaN elsewhere)."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def _env_episode(env, rng: np.random.Generator, seed: int | None) -> tuple[int, float]:
    """One RallyEnv episode with uniformly random actions: (steps, simulated s)."""
    env.reset(seed=seed)
    steps, done = 0, False
    while not done:
        _, _, done, _, info = env.step(rng.uniform(-1.0, 1.0, ACTION_SIZE))
        steps += 1
    return steps, info["time"]


def _bench_env(env, episodes: int, seed: int, say) -> dict:
    rng = np.random.default_rng(seed)
    _env_episode(env, rng, seed)  # warm-up; later resets are unseeded, as in training
    rates, lengths, simulated, total_steps, total_wall, total_cpu, ends = [], [], [], 0, 0.0, 0.0, defaultdict(int)
    for index in range(episodes):
        start, cpu = time.perf_counter(), time.process_time()
        steps, sim_time = _env_episode(env, rng, None)
        wall = time.perf_counter() - start
        total_cpu += time.process_time() - cpu
        rates.append(steps / wall)
        lengths.append(steps)
        simulated.append(sim_time)
        total_steps += steps
        total_wall += wall
        ends[env._episode.end] += 1
        say(f"  episode {index + 1}: {steps} steps, {steps / wall:.1f} steps/s, ended by {env._episode.end}")
    return {
        "actions": "uniform random in [-1, 1]^16",
        "steps_per_second": total_steps / total_wall,
        "steps_per_cpu_second": total_steps / total_cpu,
        "steps_per_second_median_episode": float(np.median(rates)),
        "episode_steps_median": float(np.median(lengths)),
        "real_time_factor": float(np.sum(simulated) / total_wall),
        "ends": dict(ends),
    }


def profile_by_system(run: Callable[[], object], simulated_seconds: float | None, top: int = 12) -> dict:
    """Runs ``run`` under the system tracer and then under cProfile (module docstring).

    Returns: ``systems``, per system name (or module for callbacks without a system), its share of
    the traced wall time and its callbacks' call counts; ``outside_systems_share``; and
    ``top_functions``, the cProfile functions with the most own time. Call counts are per
    simulated second when ``simulated_seconds`` is given."""
    spent: dict[str, float] = defaultdict(float)
    calls: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    stack: list[tuple[object, str]] = []
    names: dict[int, str] = {}
    last = [time.perf_counter()]

    def owner_of(frame) -> str | None:
        if not frame.f_code.co_filename.startswith(SYSTEMS_DIR):
            return None
        system = frame.f_locals.get("self")
        if system is None or not hasattr(system, "get_name"):
            # A helper of the systems' modules (a state's method, a lambda) counts for the system
            # that called it, or for its module when Drake called it directly.
            return None if stack else Path(frame.f_code.co_filename).stem
        key = id(system)
        if key not in names:
            names[key] = system.get_name() or type(system).__name__
        return names[key]

    def tracer(frame, event, arg):
        now = time.perf_counter()
        spent[stack[-1][1] if stack else OUTSIDE_SYSTEMS] += now - last[0]
        if event == "call":
            owner = owner_of(frame)
            if owner is not None and not (stack and stack[-1][1] == owner):
                stack.append((frame, owner))
                calls[owner][frame.f_code.co_name] += 1
        elif event == "return" and stack and stack[-1][0] is frame:
            stack.pop()
        last[0] = time.perf_counter()

    sys.setprofile(tracer)
    try:
        run()
    finally:
        sys.setprofile(None)
    total = sum(spent.values())
    per_second = 1.0 / simulated_seconds if simulated_seconds else 1.0
    systems = {
        name: {
            "share": spent[name] / total,
            "calls" + ("_per_simulated_second" if simulated_seconds else ""): {f: round(n * per_second, 1) for f, n in sorted(calls[name].items(), key=lambda item: -item[1])},
        }
        for name in sorted((n for n in spent if n != OUTSIDE_SYSTEMS), key=lambda n: -spent[n])
    }

    profiler = cProfile.Profile()
    profiler.enable()
    try:
        run()
    finally:
        profiler.disable()
    stats = pstats.Stats(profiler)
    rows = sorted(stats.stats.items(), key=lambda item: -item[1][2])[:top]
    total_profiled = max(stats.total_tt, 1e-12)
    top_functions = [
        {"function": f"{Path(file).name}:{line}({name})", "own_share": own / total_profiled, "calls": int(count)}
        for (file, line, name), (_, count, own, _, _) in rows
    ]
    return {"systems": systems, "outside_systems_share": spent[OUTSIDE_SYSTEMS] / total, "top_functions": top_functions}


def print_sim_figures(figures: dict, systems_shown: int = 8) -> None:
    """The human-readable report of ``bench_sim``'s figures (stdout)."""
    seconds = figures["simulated_seconds_per_episode"]
    print(f"rally diagram, {figures['controller']} controller, {figures['episodes']} episodes of {seconds:g} simulated s, one core:")
    for key, _, _ in RALLY_CASES:
        row = figures[f"rally_{key}"]
        print(
            f"  {row['sensors']:<54} {row['real_time_factor_median']:6.2f} x real time (median; min {row['real_time_factor_min']:.2f}; "
            f"{row['cpu_real_time_factor_median']:.2f} per CPU second)"
        )
    print(f"  statistical / cameras: {figures['ratio_statistical_to_cameras']:.2f}; "
          f"without / with the hit prediction: {figures['ratio_no_hit_prediction_to_statistical']:.2f}")
    ceilings = figures["ceilings"]
    print(
        f"  ceilings (per CPU second): the ball alone {ceilings['ball_alone_cpu_real_time_factor_median']:.2f} x real time; "
        f"the robot alone under the control stack {ceilings['controlled_robot_alone_cpu_real_time_factor_median']:.2f} x"
    )
    env = figures["env"]
    print(
        f"RallyEnv, {env['actions']}: {env['steps_per_second']:.1f} steps/s with resets ({env['steps_per_cpu_second']:.1f} per CPU s; "
        f"median episode {env['steps_per_second_median_episode']:.1f}), {env['episode_steps_median']:.0f} steps per episode, "
        f"{env['real_time_factor']:.2f} x real time; ends: {env['ends']}"
    )
    print("segment-stepped rally diagram (B = 1), same controller and shots:")
    for positions in ("cameras", "statistical"):
        row = figures[f"rally_{positions}_b1"]
        print(f"  {row['sensors']:<54} {row['real_time_factor_median']:6.2f} x real time (median; min {row['real_time_factor_min']:.2f})")
    print(f"  cameras, segment-stepped / continuous: {figures['ratio_cameras_b1_new_to_old']:.1f}")
    print("RallyVectorEnv (segment-stepped, statistical sensors), random actions:")
    for batch, row in figures["segment_env"].items():
        print(f"  B = {batch:>4}: {row['steps_per_second']:8.0f} steps/s ({row['steps_per_cpu_second']:.0f} per CPU s), {row['resident_memory_mb']:.0f} MB resident")
    print(f"  best / RallyEnv: {figures['ratio_env_steps_new_to_old']:.1f}")
    for name, profile in figures.get("profile", {}).items():
        print(f"profile ({name}): outside the systems {100 * profile['outside_systems_share']:.0f} %")
        for system, row in list(profile["systems"].items())[:systems_shown]:
            calls = next(value for key, value in row.items() if key.startswith("calls"))
            counts = ", ".join(f"{function} x{count:g}" for function, count in list(calls.items())[:3])
            print(f"  {system:<24} {100 * row['share']:5.1f} %   {counts}")
        for function in profile["top_functions"][:6]:
            print(f"    {100 * function['own_share']:5.1f} % own  {function['function']} x{function['calls']}")
