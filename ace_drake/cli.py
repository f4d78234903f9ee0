"""``ace-drake <command>``: the project's stable command-line surface.

With ``--json`` a command prints a single JSON object on stdout and nothing else; progress and
logs go to stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from ace_drake import artefacts
from ace_drake.config import ConfigError, load_config, to_dict
from ace_drake.control.params import RallyParams
from ace_drake.perception.params import PerceptionParams
from ace_drake.physics.params import BallPhysicsParams

REPO_ROOT = Path(__file__).resolve().parent.parent
MODELS = REPO_ROOT / "models"
DEFAULT_FITTED_PARAMS = MODELS / "ball_physics_fitted.yaml"


def log(message: str) -> None:
    """Progress and diagnostics: stderr, never stdout."""
    print(message, file=sys.stderr, flush=True)


def emit_json(payload: dict) -> None:
    """The single JSON object of a ``--json`` command."""
    json.dump(payload, sys.stdout, indent=2, default=_json_default)
    sys.stdout.write("\n")


def load_ball_params(path: str | None) -> BallPhysicsParams:
    """The paper's ball model, or the parameter file ``path`` (a YAML like models/ball_physics_fitted.yaml)."""
    return BallPhysicsParams() if path is None else load_config(BallPhysicsParams, path)


# ------------------------------------------------------------------------------ commands


def _rally_params(args) -> RallyParams:
    """The rally diagram's config from ``--params`` (ball model) and ``--sensors``."""
    return RallyParams(physics=load_ball_params(args.params), perception=PerceptionParams(positions=args.sensors), seed=args.seed)


def cmd_rally(args) -> int:
    """The main job: rallies of the best shipped controller against the launcher opponent."""
    from pydrake.geometry import Meshcat

    from ace_drake.evaluation.controllers import make_controller
    from ace_drake.evaluation.rallies import play_rallies, rally_rows
    from ace_drake.play.params import ShotParams

    params = _rally_params(args)
    controller = make_controller(args.controller, params)
    meshcat = Meshcat() if args.html else None
    log(f"rally: {args.rallies} rallies of '{args.controller}' against the launcher ({args.sensors} sensors, seed {args.seed})")
    played = play_rallies(controller, params, ShotParams(seed=args.seed), args.rallies, args.seed, meshcat, progress=log)
    rows = rally_rows(played)
    returned = sum(row["outcome"] == "returned" for row in rows)
    playable = sum(row["outcome"] != "invalid" for row in rows)
    if args.html:
        path = Path(args.html)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(meshcat.StaticHtml())
        log(f"wrote Meshcat replay {path} ({path.stat().st_size / 1e6:.1f} MB); open it in any browser")
    if args.json:
        emit_json({"command": "rally", "controller": args.controller, "returned": returned, "played": playable, "rallies": rows, "html": args.html})
        return 0
    print(f"{'#':>3} {'shot':<7}{'speed in':>9}{'spin in':>9}  {'outcome':<13}{'speed out':>10}{'lands at (x, y) m':>19}  reason")
    for index, row in enumerate(rows, start=1):
        out = "-" if row["outgoing_speed_m_s"] is None else f"{row['outgoing_speed_m_s']:.1f}"
        landing = "-" if row["landing_m"] is None else "({:+.2f}, {:+.2f})".format(*row["landing_m"])
        print(
            f"{index:>3} {row['shot']:<7}{row['incoming_speed_m_s']:>9.1f}{row['incoming_spin_rad_s']:>9.0f}  "
            f"{row['outcome']:<13}{out:>10}{landing:>19}  {row['reason']}"
        )
    print(f"returned {returned} of {playable} playable shots ({len(rows) - playable} invalid)")
    return 0


def cmd_evaluate(args) -> int:
    """Return-rate evaluation of a controller (``evaluation.evaluate``)."""
    from ace_drake.evaluation.controllers import NoisyActions, make_controller
    from ace_drake.evaluation.evaluate import evaluate
    from ace_drake.play.params import ShotParams
    from ace_drake.play.shots import human_shots, make_distribution

    if args.episodes is not None and args.episodes < 1:
        raise ConfigError(f"evaluate: --episodes must be >= 1, got {args.episodes}")
    params = _rally_params(args)
    players = tuple(name.strip() for name in args.players.split(",") if name.strip()) if args.players else ()
    if players and not args.data:
        raise ConfigError("evaluate: --players selects shots of --data; give a match-data CSV")
    if args.data:
        shots, serve = human_shots(args.data, players)
        shots, serve = shots[: args.episodes], serve[: args.episodes]
        of = f" of {', '.join(players)}" if players else ""
        source = f"the {len(shots)} human shots (shot_p2){of} of {args.data}"
    else:
        sample = make_distribution(ShotParams(seed=args.seed), params.physics).draw(np.random.default_rng(args.seed), args.episodes or 200)
        shots, serve = sample.states, sample.serve
        source = f"{len(shots)} shots from the built-in synthetic distribution"
    skills, skill_text = _evaluation_skills(args.skill, len(shots), params, args.seed)
    controller = make_controller(args.controller, params)
    noise = f", Gaussian action noise {args.action_noise:g}" if args.action_noise else ""
    if args.action_noise:
        controller = NoisyActions(controller, args.action_noise, seed=args.seed)
    log(f"evaluate: '{args.controller}'{noise} on {source}, {args.sensors} sensors, seed {args.seed}, {skill_text}")
    figures = evaluate(controller, params, shots, serve, args.seed, progress=log, skills=skills)
    figures = {"controller": args.controller, "action_noise": args.action_noise, "data": args.data, "players": list(players),
               "sensors": args.sensors, "seed": args.seed, "skills": args.skill or "default", **figures}
    if args.json:
        emit_json({**figures, **artefacts.provenance(), **({"data_sha256": artefacts.sha256(args.data)} if args.data else {})})
        return 0
    _print_evaluation(figures)
    return 0


def _evaluation_skills(spec: str | None, count: int, params: RallyParams, seed: int) -> tuple[np.ndarray | None, str]:
    """The skills of ``evaluate --skill``: None (the diagram's default), one fixed skill
    "Y,WP,WS" for every shot, or "sampled": one per shot from the training distribution
    (``training.env.SkillSampling``) drawn with ``seed``. Returns (skills (count, 3) or None,
    a phrase for the log); raises ConfigError for anything else."""
    from ace_drake.training.env import SkillSampling

    if spec is None:
        return None, "the default skill (y_desired 0 m, w_p 1, w_s 0)"
    if spec == "sampled":
        rng = np.random.default_rng([seed, 0x5C111])
        skills = np.array([SkillSampling().sample(rng, params.physics.table.width) for _ in range(count)]).reshape(count, 3)
        return skills, "skills sampled as in training"
    try:
        skill = np.array([float(value) for value in spec.split(",")])
    except ValueError:
        skill = np.array([])
    if skill.shape != (3,) or not np.all(np.isfinite(skill)) or not (0.0 <= skill[1] <= 1.0 and -1.0 <= skill[2] <= 1.0):
        raise ConfigError(f"evaluate: --skill must be 'sampled' or Y,WP,WS (y_desired in m, w_p in [0, 1], w_s in [-1, 1]), got {spec!r}")
    return np.tile(skill, (count, 1)), f"skill y_desired {skill[0]:g} m, w_p {skill[1]:g}, w_s {skill[2]:g}"


def _print_evaluation(figures: dict) -> None:
    def rate(entry: dict) -> str:
        if entry["rate"] is None:
            return "-"
        low, high = entry["ci95"]
        return f"{entry['rate']:.1%} [{low:.1%}, {high:.1%}] of {entry['played']}"

    noise = f" with action noise {figures['action_noise']:g}" if figures.get("action_noise") else ""
    print(f"controller {figures['controller']}{noise}: return rate {rate(figures['return_rate'])} (95% Wilson interval); {figures['invalid_shots']} unplayable shots left out")
    for key, unit in (("by_incoming_speed", "m/s"), ("by_incoming_spin", "rad/s")):
        print(f"  {key.replace('_', ' ')}:")
        for row in figures[key]:
            high = "inf" if row["high"] is None else f"{row['high']:g}"
            print(f"    [{row['low']:g}, {high}) {unit}: {rate(row)}")
    for key in ("outgoing_speed_m_s", "outgoing_spin_rad_s", "bounce_to_hit_s"):
        entry = figures[key]
        if entry is not None:
            print(f"  {key}: median {entry['median']:.3g} (p10 {entry['p10']:.3g}, p90 {entry['p90']:.3g}) over {entry['count']}")
    print("  not returned:")
    for reason, count in figures["not_returned_by_reason"].items():
        print(f"    {count:5d}  {reason}")
    skill = figures["skill"]
    aim = skill["aim"]
    if aim["error_m"] is not None:
        fit = "" if aim["slope"] is None else f"; y_land on y_desired: slope {aim['slope']:.2f}, correlation {aim['correlation']:.2f}"
        print(f"  skill ({figures['skills']}): landing y - y_desired median {aim['error_m']['median']:.3f} m "
              f"(p90 {aim['error_m']['p90']:.3f}) over {aim['count']} aimed returns{fit}")
    for group in skill["landing_topspin_rad_s"]:
        entry = group["landing_topspin_rad_s"]
        if entry is not None:
            print(f"    w_s {group['group']:<8} landing topspin median {entry['median']:.0f} rad/s (p10 {entry['p10']:.0f}, p90 {entry['p90']:.0f}) over {entry['count']}")
    if skill["mean_reward"] is not None:
        print(f"    mean eq. (10) reward {skill['mean_reward']:.3f}")
    print(f"  segments accepted {figures['segments_accepted']}, refused {figures['segments_refused']}; {figures['wall_time_s']:.0f} s")


def cmd_physics_validate(args) -> int:
    """Replay recorded (shot or bounce) -> bounce pairs through the ball model; report errors."""
    from ace_drake.analysis.physics_validation import format_summary, predict_pairs, summarize
    from ace_drake.match_data import event_pairs, load_match_events

    params = load_ball_params(args.params)
    pairs = event_pairs(load_match_events(args.data))
    if args.player:
        unknown = sorted(set(args.player) - set(pairs.players))
        if unknown:
            raise ConfigError(f"--player {unknown}: not in {args.data} (players: {sorted(set(pairs.players))})")
        pairs = pairs.subset(np.isin(pairs.players, args.player))
    log(f"replaying {len(pairs)} event pairs from {args.data} with {'the paper model' if args.params is None else args.params}")
    summary = summarize(pairs, predict_pairs(pairs, params))
    summary = {"command": "physics-validate", "data": str(args.data), "params": args.params or "paper", **summary}
    if args.json:
        emit_json(summary)
    else:
        print(format_summary(summary, f"ball model: {summary['params']}; data: {args.data}"))
    return 0


def cmd_physics_fit(args) -> int:
    """Fit aerodynamic and table coefficients on some players, judge on the held-out ones."""
    import yaml

    from ace_drake.analysis.physics_fit import DEFAULT_FIT_PARAMETERS, fit_physics
    from ace_drake.analysis.physics_validation import format_summary, predict_pairs, summarize
    from ace_drake.match_data import event_pairs, load_match_events

    pairs = event_pairs(load_match_events(args.data))
    players = sorted(set(pairs.players))
    unknown = sorted(set(args.holdout_player) - set(players))
    if unknown:
        raise ConfigError(f"--holdout-player {unknown}: not in {args.data} (players: {players})")
    held_out = np.isin(pairs.players, args.holdout_player)
    if held_out.all():
        raise ConfigError("--holdout-player: every player is held out; nothing is left to fit on")
    initial = load_ball_params(args.params)
    names = tuple(args.parameter or DEFAULT_FIT_PARAMETERS)
    fit_players = sorted(set(pairs.players[~held_out]))
    log(f"fitting {names} on {int((~held_out).sum())} pairs ({', '.join(fit_players)}); "
        f"holding out {int(held_out.sum())} pairs ({', '.join(args.holdout_player)})")
    result = fit_physics(pairs.subset(~held_out), initial, names, max_evaluations=args.max_evaluations, progress=log)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # Every field that was fitted or differs from the paper's defaults (a --params start), rounded.
    final, defaults = to_dict(result.params), to_dict(BallPhysicsParams())
    nested: dict[str, dict] = {}
    for group, fields in final.items():
        for field, value in fields.items():
            if f"{group}.{field}" in result.values or value != defaults[group][field]:
                nested.setdefault(group, {})[field] = round(value, 6) if isinstance(value, float) else value
    header = (
        "# Ball-model coefficients fitted to recorded match data by `ace-drake physics-fit`.\n"
        "# Fields not listed keep the paper's defaults (ace_drake/config.py); how this file was\n"
        f"# produced, and its held-out figures, are in {out.with_suffix('.json').name}.\n"
    )
    out.write_text(header + yaml.safe_dump(nested, sort_keys=True))
    fitted = load_ball_params(str(out))  # the figures are those of the file as written (rounded)
    figures = {}
    for label, mask in [("fit_players", ~held_out), ("held_out_players", held_out)]:
        subset = pairs.subset(mask)
        figures[label] = {
            "initial": summarize(subset, predict_pairs(subset, initial)),
            "fitted": summarize(subset, predict_pairs(subset, fitted)),
        }
    sidecar = {
        **artefacts.provenance(),
        "data": {"file": Path(args.data).name, "sha256": artefacts.sha256(args.data), "pairs": len(pairs)},
        "fit_players": fit_players,
        "held_out_players": sorted(args.holdout_player),
        "initial_params": args.params or "paper",
        "fitted": result.values,
        "optimizer": {"evaluations": result.evaluations, "message": result.message,
                      "initial_cost": result.initial_cost, "final_cost": result.final_cost},
        "figures": figures,
    }
    out.with_suffix(".json").write_text(json.dumps(sidecar, indent=2, default=_json_default) + "\n")
    log(f"wrote {out} and {out.with_suffix('.json')}")
    if args.json:
        emit_json({"command": "physics-fit", "params_file": str(out), **sidecar})
    else:
        for label in ("initial", "fitted"):
            print(format_summary(figures["held_out_players"][label], f"\nheld-out players, {label} model"))
    return 0


def cmd_sysid(args) -> int:
    """Identify each logged joint's delayed second-order model (paper eq. (9)); write the config."""
    import yaml

    from ace_drake.control.joint_model import ramp_tracking_lag
    from ace_drake.control.sysid import identify_joint, load_joint_log
    from ace_drake.robot.params import JOINT_NAMES, RobotDynamicsParams

    joint_log = load_joint_log(args.log)
    unknown = sorted(set(joint_log.commands) - set(JOINT_NAMES))
    if unknown:
        raise ConfigError(f"{args.log}: unknown joint(s) {unknown}; the robot's joints are {list(JOINT_NAMES)}")
    defaults = RobotDynamicsParams()
    identified = {}
    for name in joint_log.commands:
        log(f"identifying {name} from {joint_log.times.size} samples at {1 / joint_log.period:.0f} Hz")
        result = identify_joint(joint_log.times, joint_log.commands[name], joint_log.positions[name])
        identified[name] = result
        log(f"  K {result.process.gain:.4f}  w {result.process.natural_frequency:.1f} rad/s  "
            f"zeta {result.process.damping_ratio:.3f}  tau_d {1000 * result.process.delay:.3f} ms  fit {result.fit_percent:.2f} %")
    joints = [identified[n].params if n in identified else defaults.joints[i] for i, n in enumerate(JOINT_NAMES)]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    header = (
        "# Joint dynamics (paper eq. (9)) identified by `ace-drake sysid`; joints in the order\n"
        f"# {', '.join(JOINT_NAMES)}. Joints absent from the log keep the defaults. See {out.with_suffix('.json').name}.\n"
    )
    body = {"joints": [{"a": list(j.a), "b": list(j.b), "delay": j.delay} for j in joints],
            "command_period": joint_log.period}
    out.write_text(header + yaml.safe_dump(body, sort_keys=False))
    load_config(RobotDynamicsParams, out)  # what was written must load
    report = {
        name: {**dataclasses.asdict(r.process), "rms_error": r.rms_error, "fit_percent": r.fit_percent,
               "ramp_tracking_lag_s": ramp_tracking_lag(r.params)}
        for name, r in identified.items()
    }
    sidecar = {
        **artefacts.provenance(),
        "log": {"file": Path(args.log).name, "sha256": artefacts.sha256(args.log), "samples": int(joint_log.times.size)},
        "identified": report,
        "defaulted": [n for n in JOINT_NAMES if n not in identified],
    }
    out.with_suffix(".json").write_text(json.dumps(sidecar, indent=2) + "\n")
    log(f"wrote {out} and {out.with_suffix('.json')}")
    if args.json:
        emit_json({"params_file": str(out), **sidecar})
    return 0


def cmd_bench(args) -> int:
    """Benchmarks by name; medians and ratios measured side by side."""
    runners = {"ball": _bench_ball, "reach": _bench_reach, "control": _bench_control, "safety": _bench_safety, "perception": _bench_perception, "sim": _bench_sim, "train": _bench_train}
    if args.name not in runners:
        raise ConfigError(f"bench: unknown benchmark {args.name!r}; available: {', '.join(runners)}")
    return runners[args.name](args)


def _bench_ball(args) -> int:
    from ace_drake.analysis import bench

    figures = bench.bench_ball(repeats=args.repeats, progress=log)
    if args.json:
        emit_json(figures)
    else:
        for name, rate in figures["ball_seconds_per_wall_second"].items():
            print(f"{name:<28}{rate:>12.1f} ball-s per wall-s   (median {figures['wall_seconds_median'][name]:.3f} s per run)")
        for name, ratio in figures["ratios"].items():
            print(f"{name:<40}{ratio:>8.2f}")
    return 0


def _bench_control(args) -> int:
    from ace_drake.analysis.control_bench import bench_control

    if args.steps < 1:
        raise ConfigError(f"bench control: --steps must be >= 1, got {args.steps}")
    figures = bench_control(steps=args.steps, seed=args.seed, states=args.states, progress=log)
    if args.json:
        emit_json(figures)
        return 0
    print(f"one control step on 1 thread over {figures['steps']} steps ({figures['states']} states): median {figures['step']['median_ms']:.3f} ms, p99 {figures['step']['p99_ms']:.3f} ms")
    for name, row in figures["stages"].items():
        print(f"  {name:<10} median {row['median_ms']:.3f} ms   p99 {row['p99_ms']:.3f} ms")
    row = figures["step_without_check"]
    print(f"  all but the collision check: median {row['median_ms']:.3f} ms   p99 {row['p99_ms']:.3f} ms")
    print(f"refused steps: {figures['refused_steps']} ({', '.join(f'{k}: {n}' for k, n in figures['refusals'].items()) or 'none'})")
    qp = figures["qp"]
    print(
        f"spline QP alone ({qp['problems']} problems): DAQP median {qp['daqp']['median_ms']:.3f} ms, "
        f"MathematicalProgram + Clarabel median {qp['mathematical_program_clarabel']['median_ms']:.3f} ms "
        f"({qp['median_ratio_clarabel_to_daqp']:.0f}x)"
    )
    return 0


def _bench_safety(args) -> int:
    from ace_drake.analysis.control_bench import bench_safety

    if args.cases < 1 or args.workers < 1:
        raise ConfigError(f"bench safety: --cases and --workers must be >= 1, got {args.cases} and {args.workers}")
    figures = bench_safety(cases=args.cases, seed=args.seed, workers=args.workers, progress=log)
    if args.json:
        emit_json(figures)
        return 0
    for name, value in figures.items():
        print(f"{name:<28}{value}")
    return 0 if figures["violations"] == 0 else 1


def _bench_perception(args) -> int:
    from ace_drake.analysis.perception_bench import bench_perception

    if not args.data:
        raise ConfigError("bench perception: --data FILE (a match-data CSV with shot_p2 events) is required")
    if args.shots < 1:
        raise ConfigError(f"bench perception: --shots must be >= 1, got {args.shots}")
    figures = bench_perception(args.data, shots=args.shots, seed=args.seed, progress=log)
    figures["data_sha256"] = artefacts.sha256(args.data)
    if args.json:
        emit_json(figures)
        return 0
    tri = figures["triangulation"]
    print(
        f"triangulation over {figures['shots']} recorded shots ({tri['triggers']} triggers, {figures['pixel_noise_sigma_px']} px noise): "
        f"error mean {1e3 * tri['error_mean_m']:.2f} mm, p95 {1e3 * tri['error_p95_m']:.2f} mm; valid {100 * tri['valid_fraction']:.1f} %; "
        f"latency {1e3 * tri['latency_s']:.1f} ms; CPU {tri['cpu_median_ms']:.2f} ms median per 9-camera triangulation"
    )
    for path in ("ekf_cameras", "ekf_statistical_sensor"):
        for t, row in figures[path]["report_times"].items():
            print(f"{path} after {1e3 * float(t):.0f} ms: velocity error {row['velocity_error_mean_m_s']:.3f} m/s, spin error {row['spin_error_mean_rad_s']:.1f} rad/s")
    print(f"coverage by >= 3 cameras at >= 5 px: {100 * figures['coverage_3_views_5_px']:.1f} % of the play volume")
    return 0


def _bench_sim(args) -> int:
    from ace_drake.analysis.sim_bench import bench_sim, print_sim_figures

    if args.seconds <= 0 or args.repeats < 1:
        raise ConfigError(f"bench sim: --seconds must be > 0 and --repeats >= 1, got {args.seconds} and {args.repeats}")
    figures = bench_sim(seconds=args.seconds, episodes=args.repeats, seed=args.seed, progress=log)
    if args.json:
        emit_json(figures)
    else:
        print_sim_figures(figures)
    return 0


def _bench_train(args) -> int:
    from ace_drake.analysis.train_bench import bench_train

    if args.seconds <= 0 or args.steps < 1:
        raise ConfigError(f"bench train: --seconds must be > 0 and --steps >= 1, got {args.seconds} and {args.steps}")
    figures = bench_train(seconds=args.seconds, updates=args.steps, seed=args.seed, progress=log)
    if args.json:
        emit_json({**figures, **artefacts.provenance()})
    else:
        for workers, rate in figures["env_steps_per_s"].items():
            print(f"env steps/s with {workers} worker(s): {rate:.1f}")
        print(f"2 workers / 1 worker: {figures['worker_speedup']:.2f}")
        print(f"learner updates/s: {figures['updates_per_s']:.1f}; updates per env step (2 workers): {figures['updates_per_env_step']:.2f}")
    return 0


def _bench_reach(args) -> int:
    from ace_drake.analysis.reach import bench_reach, robot_contact_points
    from ace_drake.robot.model import RobotModel, load_scenario

    if not args.data:
        raise ConfigError("bench reach: --data FILE (a match-data CSV with shot_p1 events) is required")
    points = robot_contact_points(args.data)
    model = RobotModel(load_scenario(args.scenario))
    log(f"bench reach: {len(points)} robot contact points from {args.data}, and their mirror in y")
    figures = bench_reach(model, points, seed=args.seed, progress=log)
    figures.update({"data": args.data, "data_sha256": artefacts.sha256(args.data), "scenario": str(args.scenario or "models/scenario.yaml")})
    if args.json:
        emit_json(figures)
        return 0
    for name in ("reach", "reach_mirrored_y"):
        row = figures[name]
        print(
            f"{name:<18}{row['reached']:>5}/{row['points']:<5} reached ({100 * row['fraction_reached']:.1f}%)   "
            f"IK solve median {1e3 * row['solve_time_median_s']:.1f} ms, p99 {1e3 * row['solve_time_p99_s']:.0f} ms"
        )
    swing = figures["fastest_swing"]
    print(
        f"fastest +x swing at hitting height: {figures['max_racket_speed_x_m_s']:.1f} m/s "
        f"(racket at {swing['racket_position_m']} m, face {swing['normal_angle_deg']:.0f} deg from +x)"
    )
    return 0


def cmd_cameras(args) -> int:
    """Camera placement by CMA-ES (``perception.placement``): writes the calibration, its
    sidecar and the coverage plot."""
    from ace_drake.perception.placement import optimize_and_write

    if args.action != "optimize":
        raise ConfigError(f"cameras: unknown action {args.action!r}; expected optimize")
    if args.iterations < 1 or not args.spacing > 0.0:
        raise ConfigError(f"cameras optimize: need --iterations >= 1 and --spacing > 0 m, got {args.iterations} and {args.spacing}")
    output = Path(args.output)
    plot = Path(args.plot) if args.plot else output.with_name(output.stem + "_coverage.png")

    def progress(iteration: int, cost: float, figures) -> None:
        if iteration % 10 == 0 or iteration == args.iterations:
            log(f"cameras optimize: iteration {iteration}/{args.iterations}, coverage {100 * figures.coverage:.1f} %")

    sidecar = optimize_and_write(output, seed=args.seed, iterations=args.iterations, spacing=args.spacing, plot_path=plot,
                                 command=artefacts.provenance()["command"], progress=progress)
    log(f"wrote {output}, {output.with_suffix('.json')} and {plot}")
    if args.json:
        emit_json(sidecar)
    else:
        print(f"coverage by >= 3 views at >= 5 px: {100 * sidecar['figures']['coverage']:.1f} % of the play volume")
    return 0


def cmd_diagrams(args) -> int:
    """Render every documented diagram's graph (DOT, and SVG when Graphviz is installed)."""
    import shutil
    import subprocess

    from ace_drake.diagrams import DOCUMENTED_DIAGRAMS, graphviz_dot

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    dot_program = shutil.which("dot")
    if dot_program is None:
        log("Graphviz 'dot' not found: writing DOT only (install it with `apt-get install graphviz` "
            "or your platform's package manager to get SVGs)")
    index = ["# Diagram graphs", "", "Generated by `ace-drake diagrams`; a test checks that the DOT files are current.", ""]
    for name, build in DOCUMENTED_DIAGRAMS.items():
        dot = graphviz_dot(build())
        dot_path, svg_path = out / f"{name}.dot", out / f"{name}.svg"
        unchanged = dot_path.is_file() and dot_path.read_text() == dot
        dot_path.write_text(dot)
        line = f"- `{name}`: [{name}.dot]({name}.dot)"
        if dot_program is not None:
            subprocess.run([dot_program, "-Tsvg", "-o", str(svg_path)], input=dot, text=True, check=True)
        elif svg_path.is_file() and not unchanged:
            log(f"{svg_path} is out of date (its graph changed) and is left out of the index: install Graphviz to redraw it")
        if svg_path.is_file() and (dot_program is not None or unchanged):  # drawn now, or from the same DOT text
            line += f", [{name}.svg]({name}.svg)\n\n  ![{name}]({name}.svg)"
        index.append(line)
        log(f"wrote {dot_path}" + (" and .svg" if dot_program else ""))
    (out / "README.md").write_text("\n".join(index) + "\n")
    return 0


def cmd_train(args) -> int:
    """A training run (``training.export.train_and_export``): resumes from the run directory's
    checkpoint, trains, exports the policy with its sidecar and learning curve."""
    from ace_drake.training.export import train_and_export

    summary = train_and_export(args.config, args.run_dir, args.export_dir, args.export, args.evaluate_data, args.export_only, progress=log)
    evaluation = summary["final_evaluation"]
    if args.json:
        emit_json(summary)
    else:
        print(f"exported {summary['policy']} after {summary['env_steps']} steps, {summary['updates']} updates, {summary['wall_time_s']:.0f} s")
        if evaluation:
            rate = evaluation["return_rate"]
            print(f"return rate on {args.evaluate_data}: {rate['rate']:.1%} [{rate['ci95'][0]:.1%}, {rate['ci95'][1]:.1%}] of {rate['played']} playable shots")
            if "held_out" in evaluation:
                rate = evaluation["held_out"]["return_rate"]
                print(f"  of the held-out players ({', '.join(evaluation['held_out']['players'])}): "
                      f"{rate['rate']:.1%} [{rate['ci95'][0]:.1%}, {rate['ci95'][1]:.1%}] of {rate['played']}")
    return 0


def cmd_results(args) -> int:
    """The README's results table (and docs/benchmarks.md's) regenerated from their source files."""
    from ace_drake.analysis.results import render_results, stale_files, update_files

    if args.check:
        stale = stale_files(REPO_ROOT)
        for name in stale:
            log(f"results: {name} is stale; run `ace-drake results` and commit it")
        if not stale:
            log("results: README.md and docs/benchmarks.md are current")
        return 1 if stale else 0
    for name in update_files(REPO_ROOT):
        log(f"results: rewrote {name}")
    print(render_results(REPO_ROOT))
    return 0


# ------------------------------------------------------------------------------ parser


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ace-drake", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)

    def add_rally_options(command, controller_default):
        command.add_argument("--controller", default=controller_default, help="still, returner, returner:memoryless, returner:forget=<part>[+<part>...], returner:hit_state, returner:hit_memory or policy:<name> (default: %(default)s)")
        command.add_argument("--sensors", choices=("cameras", "statistical"), default="cameras", help="ball positions from the nine cameras + triangulator, or the training sensor model")
        command.add_argument("--seed", type=int, default=0)
        command.add_argument("--params", help="ball-model parameter YAML (default: the paper's model)")
        command.add_argument("--json", action="store_true")

    from ace_drake.evaluation.controllers import DEFAULT_CONTROLLER

    rally = commands.add_parser("rally", help="the main job: rallies of the best shipped controller against the launcher; Meshcat replay")
    add_rally_options(rally, DEFAULT_CONTROLLER)
    rally.add_argument("--rallies", type=int, default=5, help="how many rallies (default: %(default)s)")
    rally.add_argument("--html", default="out/rally.html", help="Meshcat replay to write ('' for none)")
    rally.set_defaults(run=cmd_rally)

    evaluate = commands.add_parser("evaluate", help="return-rate evaluation of a controller (paper Fig. 3c-g)")
    add_rally_options(evaluate, DEFAULT_CONTROLLER)
    evaluate.add_argument("--data", help="match-data CSV: one episode per human shot (shot_p2); default: the synthetic distribution")
    evaluate.add_argument("--players", help="with --data: only these players' shots, comma-separated player_id values (e.g. 'Elite D,Elite E')")
    evaluate.add_argument("--episodes", type=int, help="at most this many episodes (default: all shots of --data, or 200)")
    evaluate.add_argument("--skill", help="the skill of every episode: Y,WP,WS (y_desired m, w_p, w_s) or 'sampled' (one per shot from the training distribution, seeded); default: 0,1,0")
    evaluate.add_argument("--action-noise", type=float, default=0.0, help="add Gaussian noise of this std (action units) to every action, seeded (default: none)")
    evaluate.set_defaults(run=cmd_evaluate)

    train = commands.add_parser("train", help="train the rally policy (SAC; resumable) and export it")
    train.add_argument("config", help="training config YAML (training.loop.TrainConfig; e.g. models/train_rally_hit_state.yaml)")
    train.add_argument("--run-dir", help="checkpoints and TensorBoard logs (default out/train/<name>); an existing one resumes")
    train.add_argument("--export-dir", default=str(MODELS / "policies"), help="where the policy, sidecar and curve go (default: %(default)s)")
    train.add_argument("--export", choices=("best", "final"), default="best", help="the best evaluated actor or the final one")
    train.add_argument("--evaluate-data", help="match-data CSV: evaluate the exported policy on its human shots (cameras) into the sidecar")
    train.add_argument("--export-only", action="store_true", help="export the run's checkpoint as it stands (e.g. a run stopped early) without training")
    train.add_argument("--json", action="store_true")
    train.set_defaults(run=cmd_train)

    validate = commands.add_parser("physics-validate", help="replay recorded events through the ball model")
    validate.add_argument("--data", required=True, help="match-data CSV (format of ace_match_events_elite.csv)")
    validate.add_argument("--params", help="ball-model parameter YAML (default: the paper's model)")
    validate.add_argument("--player", action="append", help="only these players (repeatable)")
    validate.add_argument("--json", action="store_true")
    validate.set_defaults(run=cmd_physics_validate)

    fit = commands.add_parser("physics-fit", help="fit ball-model coefficients on some players")
    fit.add_argument("--data", required=True, help="match-data CSV")
    fit.add_argument("--holdout-player", action="append", required=True, help="player to hold out (repeatable)")
    fit.add_argument("--parameter", action="append", help="coefficient to fit (repeatable; default: all of FIT_BOUNDS)")
    fit.add_argument("--params", help="starting parameter YAML (default: the paper's model)")
    fit.add_argument("--out", default=str(DEFAULT_FITTED_PARAMS), help="where to write the fitted YAML (+ .json sidecar)")
    fit.add_argument("--max-evaluations", type=int, default=200)
    fit.add_argument("--json", action="store_true")
    fit.set_defaults(run=cmd_physics_fit)

    sysid = commands.add_parser("sysid", help="identify the joints' delayed LTI models from a log")
    sysid.add_argument("--log", required=True, help="CSV: time, <joint>_command, <joint>_position per joint")
    sysid.add_argument("--out", default=str(MODELS / "joint_dynamics_identified.yaml"))
    sysid.add_argument("--json", action="store_true")
    sysid.set_defaults(run=cmd_sysid)

    bench = commands.add_parser("bench", help="benchmarks (medians, p99, ratios)")
    bench.add_argument("name", help="which benchmark: ball, reach, control, safety, perception, sim, train")
    bench.add_argument("--repeats", type=int, default=5, help="ball: timed runs per case; sim: timed rally episodes per sensor path")
    bench.add_argument("--seconds", type=float, default=1.0, help="sim: simulated seconds per rally episode; train: wall seconds of collection per worker count")
    bench.add_argument("--data", help="reach: match-data CSV whose shot_p1 events are the contact points; perception: whose shot_p2 events are the incoming shots")
    bench.add_argument("--shots", type=int, default=50, help="perception: incoming shots")
    bench.add_argument("--scenario", help="reach: robot scenario YAML (default models/scenario.yaml)")
    bench.add_argument("--seed", type=int, default=0, help="reach: seed of the swing-speed search; control, safety: of the states and actions")
    bench.add_argument("--steps", type=int, default=1000, help="control: timed control steps; train: timed learner updates")
    bench.add_argument("--states", choices=("rally", "random"), default="rally", help="control: rally strokes (default) or a uniformly random policy (stress)")
    bench.add_argument("--cases", type=int, default=1000, help="safety: random cases (start state + action sequence)")
    bench.add_argument("--workers", type=int, default=1, help="safety: processes (the figures do not depend on it)")
    bench.add_argument("--json", action="store_true")
    bench.set_defaults(run=cmd_bench)

    cameras = commands.add_parser("cameras", help="camera placement: `cameras optimize` (CMA-ES)")
    cameras.add_argument("action", help="optimize")
    cameras.add_argument("--seed", type=int, default=0)
    cameras.add_argument("--iterations", type=int, default=300, help="CMA-ES generations")
    cameras.add_argument("--spacing", type=float, default=0.2, help="grid spacing of the play volume, m")
    cameras.add_argument("--output", default=str(REPO_ROOT / "models" / "cameras.yaml"), help="calibration file to write")
    cameras.add_argument("--plot", default="", help="coverage plot (default: <output>_coverage.png)")
    cameras.add_argument("--json", action="store_true")
    cameras.set_defaults(run=cmd_cameras)

    graphs = commands.add_parser("diagrams", help="render every diagram's graph into diagrams/")
    graphs.add_argument("--out", default=str(REPO_ROOT / "diagrams"))
    graphs.set_defaults(run=cmd_diagrams)

    results = commands.add_parser("results", help="regenerate the README's results table from the sidecars and stored JSON")
    results.add_argument("--check", action="store_true", help="only check: exit 1 if README.md or docs/benchmarks.md is stale")
    results.set_defaults(run=cmd_results)
    return parser


def main(argv: list[str] | None = None) -> int:
    artefacts.record_command_line(sys.argv[1:] if argv is None else argv)  # for the sidecars' provenance
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (ConfigError, ValueError, FileNotFoundError) as error:
        log(f"ace-drake {args.command}: error: {error}")
        return 2


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


if __name__ == "__main__":
    sys.exit(main())
