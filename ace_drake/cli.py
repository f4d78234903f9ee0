"""``ace-drake <command>``: the project's stable command-line surface.

With ``--json`` a command prints a single JSON object on stdout and nothing else; progress and
logs go to stderr. This module parses the arguments, reports input errors and prints; the work of
every command is a function of an application module (``WORK``).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from ace_drake import artefacts
from ace_drake.analysis.results import render_results, stale_files, update_files
from ace_drake.config import MODELS_DIR, ConfigError, InputError
from ace_drake.contracts import DEFAULT_CONTROLLER

REPO_ROOT = MODELS_DIR.parent
DEFAULT_FITTED_PARAMS = MODELS_DIR / "ball_physics_fitted.yaml"
SERVE_REPEATS = 50  # `serves search` and `serves evaluate`: noisy executions of each serve unless --repeats

# The function that does each command's work, "module:function", imported by ``work`` when the
# command runs and not at the top of this module: these modules load Drake, torch or Ray (seconds
# each), and ``ace-drake --help``, an input error or ``ace-drake results`` need none of them.
WORK = {
    "rally": "ace_drake.evaluation.match:run_match",
    "rally controller": "ace_drake.evaluation.controllers:best_controller",
    "match replay": "ace_drake.analysis.match_replay:write_match_replay",
    "evaluate": "ace_drake.evaluation.evaluate:evaluate_controller",
    "evaluate --skill sampled": "ace_drake.training.env:SkillSampling",
    "physics-validate": "ace_drake.analysis.physics_validation:validate_file",
    "physics summary": "ace_drake.analysis.physics_validation:format_summary",
    "physics-fit": "ace_drake.analysis.physics_fit:fit_and_write",
    "physics-fit-racket": "ace_drake.analysis.racket_fit:fit_racket_and_write",
    "physics-validate racket": "ace_drake.analysis.racket_fit:validate_racket",
    "racket figures": "ace_drake.analysis.racket_fit:format_racket_figures",
    "physics-validate trajectories": "ace_drake.analysis.trajectory_validation:validate_trajectories_with_params",
    "trajectory figures": "ace_drake.analysis.trajectory_validation:format_trajectory_figures",
    "sysid": "ace_drake.control.sysid:identify_and_write",
    "bench ball": "ace_drake.analysis.bench:bench_ball",
    "bench reach": "ace_drake.analysis.reach:bench_reach_on_file",
    "bench control": "ace_drake.analysis.control_bench:bench_control",
    "bench safety": "ace_drake.analysis.control_bench:bench_safety",
    "bench perception": "ace_drake.analysis.perception_bench:bench_perception",
    "bench sim": "ace_drake.analysis.sim_bench:bench_sim",
    "bench sim text": "ace_drake.analysis.sim_bench:print_sim_figures",
    "bench train": "ace_drake.analysis.train_bench:bench_train",
    "cameras optimize": "ace_drake.perception.placement:optimize_and_write",
    "diagrams": "ace_drake.analysis.graphs:write_graphs",
    "train": "ace_drake.training.export:train_and_export",
    "serves search": "ace_drake.analysis.serve_search:search_serves",
    "serves evaluate": "ace_drake.evaluation.serves:evaluate_library",
    "serves replan": "ace_drake.analysis.serve_search:replan_serves",
}


def work(name: str):
    """The function of ``WORK[name]``, its module imported now."""
    module, function = WORK[name].split(":")
    return getattr(importlib.import_module(module), function)


def log(message: str) -> None:
    """Progress and diagnostics: stderr, never stdout."""
    print(message, file=sys.stderr, flush=True)


def emit_json(payload: dict) -> None:
    """The single JSON object of a ``--json`` command (``artefacts.dumps``: a number that is not
    finite is written as null, so the output is always valid JSON)."""
    sys.stdout.write(artefacts.dumps(payload) + "\n")


# ------------------------------------------------------------------------------ commands


def cmd_rally(args) -> int:
    """The main job: a match under ITTF rules of the best shipped controller and its serves against
    a simulated opponent fitted to a recorded player (``evaluation.match.run_match``)."""
    html = Path(args.html) if args.html else None
    if html is not None and html.suffix != ".html":
        raise ConfigError(f"rally: --html must name an .html file (or '' for none), got {args.html}")
    controller = args.controller
    if controller is None:
        controller, rate = work("rally controller")()
        log(f"rally: controller {controller}" + ("" if rate is None else f" (returned {rate:.1%} of the held-out players' playable shots)"))
    result, track = work("rally")(controller, args.opponent, args.data, args.best_of, args.golden_point, args.matches, args.sensors,
                                  args.seed, args.params, args.serves, batch=args.batch, record=html is not None, progress=log)
    if html is not None:
        html.parent.mkdir(parents=True, exist_ok=True)
        partial = html.with_name(html.name + ".partial")
        work("match replay")(track, partial, progress=log)
        partial.replace(html)
        log(f"wrote the Meshcat replay of the first match: {html} ({html.stat().st_size / 1e6:.1f} MB; open it in any browser, its points are listed on the right)")
    if args.json:
        emit_json({"command": "rally", **result, "html": None if html is None else str(html)})
        return 0
    _print_match(result)
    return 0


def _print_match(result: dict) -> None:
    """The text of ``rally`` without ``--json``: the first match point by point, then the
    figures of all matches."""
    print(f"{'#':>3} {'game':>4} {'score':>6}  {'server':<7}{'serve':<18}{'strikes':>8}  {'point to':<9}how it ended")
    for index, row in enumerate(result["points"], start=1):
        robot, human = row["score"]
        winner = "let" if row["winner"] is None else row["winner"]
        serve = row["serve"] or "-"
        law = f" ({row['law']})" if row["law"] else ""
        print(f"{index:>3} {row['game']:>4} {robot:>3}-{human:<2}  {row['server']:<7}{serve:<18}{row['strikes']:>8}  {winner:<9}{row['reason']}{law}")
    for number, match in enumerate(result["matches"], start=1):
        games = ", ".join(f"{r}-{h}" for r, h in match["games"])
        print(f"match {number}: {match['winner']} won {games} against {result['opponent']}: points {match['points_won']}-"
              f"{match['points_played'] - match['points_won']}, rally length {match['rally_length_mean']:.1f} +- {match['rally_length_std']:.1f} strikes, "
              f"aces {match['aces']}, service faults {match['service_faults']}, lets {match['lets']}")
    total = result["match"]
    if total["matches"] > 1:
        print(f"all {total['matches']} matches: won {total['matches_won']}, games {total['games_won']} of {len(total['games'])}, points "
              f"{total['points_won']} of {total['points_played']}, rally length {total['rally_length_mean']:.1f} +- {total['rally_length_std']:.1f}")


def cmd_evaluate(args) -> int:
    """Return-rate evaluation of a controller (``evaluation.evaluate.evaluate_controller``)."""
    players = tuple(name.strip() for name in args.players.split(",") if name.strip()) if args.players else ()
    sampling = work("evaluate --skill sampled")() if args.skill == "sampled" else None
    figures = work("evaluate")(args.controller, sensors=args.sensors, seed=args.seed, ball_params=args.params, data=args.data,
                               players=players, episodes=args.episodes, skill=args.skill, skill_sampling=sampling,
                               action_noise=args.action_noise, stepping=args.stepping, batch=args.batch, progress=log, repeats=args.repeats)
    if args.json:
        emit_json(figures)
        return 0
    _print_evaluation(figures)
    return 0


def _print_evaluation(figures: dict) -> None:
    """The text of ``evaluate`` without ``--json``."""
    def rate(entry: dict) -> str:
        if entry["rate"] is None:
            return "-"
        low, high = entry["ci95"]
        return f"{entry['rate']:.1%} [{low:.1%}, {high:.1%}] of {entry['played']}"

    noise = f" with action noise {figures['action_noise']:g}" if figures.get("action_noise") else ""
    repeats = figures.get("repeats", 1)
    interval = "95% Wilson interval" if repeats == 1 else f"each shot {repeats} times; 95% Wilson interval over the effective number of episodes"
    print(f"controller {figures['controller']}{noise}: return rate {rate(figures['return_rate'])} ({interval}); {figures['invalid_shots']} unplayable episodes left out")
    if repeats > 1:
        rates = ", ".join(f"{entry['rate']:.1%}" if entry["rate"] is not None else "-" for entry in figures["return_rate_by_repeat"])
        print(f"  by repeat (seeds {figures['seed']}-{figures['seed'] + repeats - 1}): {rates}")
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
    """The ball model against recorded data: (shot or bounce) -> bounce pairs of match events
    (--data), measured racket contacts (--racket-contacts), measured trajectories (--trajectories);
    any of them in one run, one JSON object (the match-event figures at the top level; the racket
    contacts' under ``racket`` with their ``contacts``, ``skipped_rows``, ``racket_model`` and
    ``residual`` beside it; the trajectories' under ``trajectories``)."""
    if not (args.data or args.racket_contacts or args.trajectories):
        raise ConfigError("physics-validate: give --data, --racket-contacts or --trajectories (or several)")
    if args.player and not args.data:
        raise ConfigError("physics-validate: --player selects players of --data")
    if args.residual and not args.racket_contacts:
        raise ConfigError("physics-validate: --residual applies to --racket-contacts")
    summary: dict = {"command": "physics-validate", "params": args.params or "paper"}
    if args.data:
        summary.update(work("physics-validate")(args.data, args.params, args.player or (), progress=log))
    if args.racket_contacts:
        summary.update(work("physics-validate racket")(args.racket_contacts, args.params, args.residual))
    if args.trajectories:
        summary.update(work("physics-validate trajectories")(args.trajectories, args.params, progress=log))
    if args.json:
        emit_json(summary)
        return 0
    if args.data:
        print(work("physics summary")(summary, f"ball model: {summary['params']}; data: {args.data}"))
    if args.racket_contacts:
        racket = summary["racket"]
        print(work("racket figures")({summary["racket_model"]: racket},
                                     f"racket contacts: {summary['contacts']} of {args.racket_contacts}"
                                     + (f" ({sum(summary['skipped_rows'].values())} rows skipped)" if summary["skipped_rows"] else "")))
    if args.trajectories:
        print(work("trajectory figures")(summary))
    return 0


def cmd_physics_fit_racket(args) -> int:
    """Identify the racket contact model (eqs (7)-(8)) and its residual network on measured
    contacts, split by game; report on the held-out games."""
    games = tuple(name.strip() for name in args.holdout_games.split(",") if name.strip()) if args.holdout_games else ()
    if games and args.holdout_fraction is not None:
        raise ConfigError("physics-fit-racket: give --holdout-fraction or --holdout-games, not both")
    sidecar = work("physics-fit-racket")(args.data, args.holdout_fraction, games, args.seed, args.params, args.out, args.residual_out,
                                         epochs=args.epochs, progress=log)
    if args.json:
        emit_json({"command": "physics-fit-racket", "params_file": str(args.out), **sidecar})
        return 0
    for part in ("held_out", "training"):
        print(work("racket figures")(sidecar["figures"][part], f"\n{part.replace('_', '-')} contacts ({sidecar['split'][part + '_contacts']})"))
    print(f"\nkept the {sidecar['law']} law; wrote {args.out} and {args.residual_out} (with sidecars)")
    return 0


def cmd_physics_fit(args) -> int:
    """Fit aerodynamic and table coefficients on some players, judge on the held-out ones."""
    sidecar = work("physics-fit")(args.data, args.holdout_player, args.parameter, args.params, args.out, args.max_evaluations, progress=log)
    if args.json:
        emit_json({"command": "physics-fit", "params_file": str(args.out), **sidecar})
    else:
        for label in ("initial", "fitted"):
            print(work("physics summary")(sidecar["figures"]["held_out_players"][label], f"\nheld-out players, {label} model"))
    return 0


def cmd_sysid(args) -> int:
    """Identify each logged joint's delayed second-order model (paper eq. (9)); write the config."""
    sidecar = work("sysid")(args.log, args.out, progress=log)
    if args.json:
        emit_json({"params_file": str(args.out), **sidecar})
    return 0


def cmd_bench(args) -> int:
    """Benchmarks by name; medians and ratios measured side by side."""
    runners = {"ball": _bench_ball, "reach": _bench_reach, "control": _bench_control, "safety": _bench_safety, "perception": _bench_perception, "sim": _bench_sim, "train": _bench_train}
    if args.name not in runners:
        raise ConfigError(f"bench: unknown benchmark {args.name!r}; available: {', '.join(runners)}")
    return runners[args.name](args)


def _bench_ball(args) -> int:
    figures = work("bench ball")(repeats=args.repeats, progress=log)
    if args.json:
        emit_json(figures)
    else:
        for name, rate in figures["ball_seconds_per_wall_second"].items():
            print(f"{name:<28}{rate:>12.1f} ball-s per wall-s   (median {figures['wall_seconds_median'][name]:.3f} s per run)")
        for name, ratio in figures["ratios"].items():
            print(f"{name:<40}{ratio:>8.2f}")
    return 0


def _bench_control(args) -> int:
    if args.steps < 1:
        raise ConfigError(f"bench control: --steps must be >= 1, got {args.steps}")
    figures = work("bench control")(steps=args.steps, seed=args.seed, states=args.states, progress=log)
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
    if args.cases < 1 or args.workers < 1:
        raise ConfigError(f"bench safety: --cases and --workers must be >= 1, got {args.cases} and {args.workers}")
    figures = work("bench safety")(cases=args.cases, seed=args.seed, workers=args.workers, progress=log)
    if args.json:
        emit_json(figures)
        return 0
    for name, value in figures.items():
        print(f"{name:<28}{value}")
    return 0 if figures["violations"] == 0 else 1


def _bench_perception(args) -> int:
    if not args.data:
        raise ConfigError("bench perception: --data FILE (a match-data CSV with shot_p2 events) is required")
    if args.shots < 1:
        raise ConfigError(f"bench perception: --shots must be >= 1, got {args.shots}")
    figures = work("bench perception")(args.data, shots=args.shots, seed=args.seed, progress=log)
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
    if args.seconds <= 0 or args.repeats < 1:
        raise ConfigError(f"bench sim: --seconds must be > 0 and --repeats >= 1, got {args.seconds} and {args.repeats}")
    figures = work("bench sim")(seconds=args.seconds, episodes=args.repeats, seed=args.seed, progress=log)
    if args.json:
        emit_json(figures)
    else:
        work("bench sim text")(figures)
    return 0


def _bench_train(args) -> int:
    if args.seconds <= 0 or args.steps < 1:
        raise ConfigError(f"bench train: --seconds must be > 0 and --steps >= 1, got {args.seconds} and {args.steps}")
    figures = work("bench train")(seconds=args.seconds, updates=args.steps, seed=args.seed, progress=log)
    if args.json:
        emit_json(figures)
    else:
        for workers, rate in figures["env_steps_per_s"].items():
            print(f"env steps/s with {workers} worker(s): {rate:.1f}")
        print(f"2 workers / 1 worker: {figures['worker_speedup']:.2f}")
        for batch, rate in figures["vector_env_steps_per_s"].items():
            print(f"env steps/s with 2 workers of RallyVectorEnv B = {batch}: {rate:.0f}")
        if figures["ratio_env_steps_new_to_old"] is not None:
            print(f"best vector / RallyEnv (2 workers each): {figures['ratio_env_steps_new_to_old']:.1f}")
        updates = ", ".join(f"{rate:.1f} with {threads} thread(s)" for threads, rate in figures["updates_per_s"].items())
        print(f"learner updates/s: {updates}; updates per env step at the best collection: {figures['updates_per_env_step']:.3f}")
    return 0


def _bench_reach(args) -> int:
    if not args.data:
        raise ConfigError("bench reach: --data FILE (a match-data CSV with shot_p1 events) is required")
    figures = work("bench reach")(args.data, args.scenario, seed=args.seed, progress=log)
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
    """Camera placement by CMA-ES (``perception.placement.optimize_and_write``): writes the
    calibration, its sidecar and the coverage plot."""
    if args.action != "optimize":
        raise ConfigError(f"cameras: unknown action {args.action!r}; expected optimize")
    if args.iterations < 1 or not args.spacing > 0.0:
        raise ConfigError(f"cameras optimize: need --iterations >= 1 and --spacing > 0 m, got {args.iterations} and {args.spacing}")
    output = Path(args.output)
    plot = Path(args.plot) if args.plot else output.with_name(output.stem + "_coverage.png")

    def progress(iteration: int, cost: float, figures) -> None:
        if iteration % 10 == 0 or iteration == args.iterations:
            log(f"cameras optimize: iteration {iteration}/{args.iterations}, coverage {100 * figures.coverage:.1f} %")

    sidecar = work("cameras optimize")(output, seed=args.seed, iterations=args.iterations, spacing=args.spacing, plot_path=plot, progress=progress)
    log(f"wrote {output}, {output.with_suffix('.json')} and {plot}")
    if args.json:
        emit_json(sidecar)
    else:
        print(f"coverage by >= 3 views at >= 5 px: {100 * sidecar['figures']['coverage']:.1f} % of the play volume")
    return 0


def cmd_diagrams(args) -> int:
    """Render every documented diagram's graph (DOT, and SVG when Graphviz is installed)."""
    work("diagrams")(args.out, progress=log)
    return 0


def cmd_train(args) -> int:
    """A training run (``training.export.train_and_export``): resumes from the run directory's
    checkpoint, trains, exports the policy with its sidecar and learning curve."""
    summary = work("train")(args.config, args.run_dir, args.export_dir, args.export, args.evaluate_data, args.export_only, progress=log,
                            overwrite=args.overwrite, earlier_stage=args.earlier_stage, resume_from=args.resume_from)
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


def cmd_serves(args) -> int:
    """The serve library: ``serves search`` (the GA, the robot's plans, noisy repeats on the
    segment-stepped diagram; writes the library), ``serves evaluate`` (measures a library) and
    ``serves replan`` (re-makes a library on the current robot from its genes; writes it)."""
    if args.action != "replan":  # replan: the library's own repeats and seed unless given
        args.repeats = SERVE_REPEATS if args.repeats is None else args.repeats
        args.seed = 0 if args.seed is None else args.seed
    if (args.repeats is not None and args.repeats < 1) or args.batch < 1:
        raise ConfigError(f"serves {args.action}: need --repeats >= 1 and --batch >= 1, got {args.repeats} and {args.batch}")
    if args.action in ("search", "replan") and Path(args.out).suffix != ".npz":
        raise ConfigError(f"serves {args.action}: --out must name a .npz file, got {args.out}")
    if args.action == "search":
        kinds = [kind.strip() for kind in args.kinds.split(",") if kind.strip()]
        seeds = _integers(args.seeds, "--seeds")
        if args.generations < 1:
            raise ConfigError(f"serves search: --generations must be >= 1, got {args.generations}")
        library, summary = work("serves search")(kinds, seeds, repeats=args.repeats, seed=args.seed, generations=args.generations,
                                                 batch=args.batch, out=args.out, extend=args.extend, progress=log, executed=args.executed)
    elif args.action == "replan":
        library, summary = work("serves replan")(args.library, repeats=args.repeats, seed=args.seed, batch=args.batch, out=args.out, progress=log)
    if args.action in ("search", "replan"):
        figures = {"library": args.out, **{key: value for key, value in summary.items() if key != "candidates"},
                   "serves": [{"name": serve.name, "kind": serve.kind, **serve.stats.as_dict()} for serve in library.serves]}
    else:
        figures = work("serves evaluate")(args.library, repeats=args.repeats, seed=args.seed, batch=args.batch, progress=log)
    if args.json:
        emit_json(figures)
        return 0
    print(f"{'serve':<22}{'legal':>7}{'lets':>7}{'faults':>8}  {'lands at (x, y) m':<24}{'speed m/s':>10}{'topspin':>9}{'sidespin':>9}")
    for row in figures["serves"]:
        mean, std = row["landing_mean_m"], row["landing_std_m"]
        landing = "-" if mean[0] is None else f"({mean[0]:+.2f}, {mean[1]:+.2f}) +-{max(std):.2f}"
        speed = "-" if row["speed_mean_m_s"] is None else f"{row['speed_mean_m_s']:.1f}"
        spins = ["-" if row[key] is None else f"{row[key]:.0f}" for key in ("topspin_mean_rad_s", "sidespin_mean_rad_s")]
        print(f"{row['name']:<22}{row['legal_fraction']:>7.0%}{row['let_fraction']:>7.0%}{row['fault_fraction']:>8.0%}  {landing:<24}{speed:>10}{spins[0]:>9}{spins[1]:>9}")
    return 0


def _integers(text: str, option: str) -> list[int]:
    """A comma-separated list of integers or ranges "a-b" (inclusive), e.g. "0-9,20"."""
    values = []
    for part in (p.strip() for p in text.split(",") if p.strip()):
        try:
            low, _, high = part.partition("-") if not part.startswith("-") else (part, "", "")
            values += list(range(int(low), int(high) + 1)) if high else [int(low)]
        except ValueError:
            raise ConfigError(f"{option}: expected integers or ranges like 0-9, got {part!r}") from None
    if not values:
        raise ConfigError(f"{option}: expected at least one integer, got {text!r}")
    return values


# ------------------------------------------------------------------------------ parser


def build_parser() -> argparse.ArgumentParser:
    """The parser of every sub-command; each one's ``run`` is its handler above."""
    parser = argparse.ArgumentParser(prog="ace-drake", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)

    def add_rally_options(command, controller_default):
        default_text = "%(default)s" if controller_default else "the controller that returned the most of the held-out players' shots (docs/results/heldout/)"
        command.add_argument("--controller", default=controller_default,
                             help=f"still, returner or policy:<name>, a shipped policy of models/policies (default: {default_text})")
        command.add_argument("--sensors", choices=("cameras", "statistical"), default="cameras", help="ball positions from the nine cameras + triangulator, or the training sensor model")
        command.add_argument("--seed", type=int, default=0)
        command.add_argument("--params", help="ball-model parameter YAML (default: the paper's model)")
        command.add_argument("--json", action="store_true")

    rally = commands.add_parser("rally", help="the main job: a best-of-3 match under ITTF rules against a simulated recorded player; Meshcat replay")
    add_rally_options(rally, None)
    rally.add_argument("--opponent", default="Elite C", help="the recorded player whose fitted model plays the robot (default: %(default)s)")
    rally.add_argument("--data", help="match-data CSV the opponent is fitted on (default: ../shared/data/ace_match_events_elite.csv beside the project)")
    rally.add_argument("--best-of", type=int, default=3, help="games in the longest match, a positive odd number (default: %(default)s)")
    rally.add_argument("--golden-point", action="store_true", help="at 10-10 the next point wins the game (the paper's matches; not ITTF)")
    rally.add_argument("--matches", type=int, default=1, help="matches to play (default: %(default)s)")
    rally.add_argument("--serves", help="serve library (default: models/serve_library.npz)")
    rally.add_argument("--html", default="out/match.html", help="Meshcat replay of the first match to write (default: %(default)s); '' for none")
    rally.add_argument("--batch", type=int, default=8, help="matches played at once on the batched diagram (default: %(default)s)")
    rally.set_defaults(run=cmd_rally)

    evaluate = commands.add_parser("evaluate", help="return-rate evaluation of a controller (paper Fig. 3c-g)")
    add_rally_options(evaluate, DEFAULT_CONTROLLER)
    evaluate.add_argument("--data", help="match-data CSV: one episode per human shot (shot_p2); default: the synthetic distribution")
    evaluate.add_argument("--players", help="with --data: only these players' shots, comma-separated player_id values (e.g. 'Elite D,Elite E')")
    evaluate.add_argument("--episodes", type=int, help="at most this many episodes (default: all shots of --data, or 200)")
    evaluate.add_argument("--skill", help="the skill of every episode: Y,WP,WS (y_desired m, w_p, w_s) or 'sampled' (one per shot from the training distribution, seeded); default: 0,1,0")
    evaluate.add_argument("--action-noise", type=float, default=0.0, help="add Gaussian noise of this std (action units) to every action, seeded (default: none)")
    evaluate.add_argument("--stepping", choices=("segment", "continuous"), default="segment",
                          help="the batched segment-stepped diagram, or the continuous-time reference one episode at a time (default: %(default)s)")
    evaluate.add_argument("--batch", type=int, default=32, help="episodes played at once on the segment-stepped diagram (default: %(default)s)")
    evaluate.add_argument("--repeats", type=int, default=1,
                          help="play every shot this many times, with seeds --seed, --seed + 1, ... for the noise (the shots and skills stay those of --seed); "
                               "the figures pool them, the intervals over the effective number of episodes (default: %(default)s)")
    evaluate.set_defaults(run=cmd_evaluate)

    train = commands.add_parser("train", help="train the rally policy (SAC; resumable) and export it")
    train.add_argument("config", help="training config YAML (training.loop.TrainConfig; e.g. models/train_rally_hit_state_braking.yaml)")
    train.add_argument("--run-dir", help="checkpoints and TensorBoard logs (default out/train/<name>); an existing one resumes")
    train.add_argument("--export-dir", default=str(MODELS_DIR / "policies"), help="where the policy, sidecar and curve go (default: %(default)s)")
    train.add_argument("--export", choices=("best", "final", "actor"), default="best",
                       help="the best evaluated actor, the final one (its average, where the run keeps one), or the final actor itself")
    train.add_argument("--evaluate-data", help="match-data CSV: evaluate the exported policy on its human shots (cameras) into the sidecar")
    train.add_argument("--export-only", action="store_true", help="export the run's checkpoint as it stands (e.g. a run stopped early) without training")
    train.add_argument("--overwrite", action="store_true", help="replace a policy of the same name in --export-dir (refused otherwise)")
    train.add_argument("--earlier-stage", metavar="CHECKPOINT",
                       help="a checkpoint of the config's after: stage (e.g. its checkpoint.portable.pt) to start from instead of running "
                            "that stage in RUN_DIR/after")
    train.add_argument("--resume-from", metavar="CHECKPOINT",
                       help="a checkpoint of this run written elsewhere (e.g. its checkpoint.portable.pt, carried to a machine without "
                            "RUN_DIR) to resume from, for a RUN_DIR without one; a portable one's tables fill anew")
    train.add_argument("--json", action="store_true")
    train.set_defaults(run=cmd_train)

    validate = commands.add_parser("physics-validate", help="the ball model against recorded match events, racket contacts, trajectories")
    validate.add_argument("--data", help="match-data CSV (format of ace_match_events_elite.csv): (shot or bounce) -> bounce pairs")
    validate.add_argument("--racket-contacts", help="measured racket contacts (format of sony_racket_contacts.csv)")
    validate.add_argument("--trajectories", help="measured trajectories: CSV trajectory,t,x,y,z,wx,wy,wz (m, s, rad/s); "
                          "reported for --params beside the paper's, the match-fitted, the authors' aerodynamics and zero spin")
    validate.add_argument("--params", help="ball-model parameter YAML (default: the paper's model), e.g. models/racket_fitted.yaml")
    validate.add_argument("--residual", help="with --racket-contacts: a racket residual network (default: the one --params names, if any)")
    validate.add_argument("--player", action="append", help="with --data: only these players (repeatable)")
    validate.add_argument("--json", action="store_true")
    validate.set_defaults(run=cmd_physics_validate)

    fit_racket = commands.add_parser("physics-fit-racket", help="identify the racket contact model and its residual on measured contacts")
    fit_racket.add_argument("--data", required=True, help="measured racket contacts (format of sony_racket_contacts.csv)")
    fit_racket.add_argument("--holdout-fraction", type=float, help="hold out this fraction of the games, drawn with --seed (default 0.2)")
    fit_racket.add_argument("--holdout-games", help="hold out these games, comma-separated (e.g. 'session_2/game_1,session_6/game_0')")
    fit_racket.add_argument("--seed", type=int, default=0, help="the held-out games' draw and the residual network's training")
    fit_racket.add_argument("--params", help="starting ball-model YAML (default: the paper's model)")
    fit_racket.add_argument("--out", default=str(MODELS_DIR / "racket_fitted.yaml"), help="the fitted ball-model YAML (+ .json sidecar)")
    fit_racket.add_argument("--residual-out", default=str(MODELS_DIR / "racket_residual.pt"), help="the residual network (+ .json sidecar)")
    fit_racket.add_argument("--epochs", type=int, default=500, help="the residual network's training epochs at most")
    fit_racket.add_argument("--json", action="store_true")
    fit_racket.set_defaults(run=cmd_physics_fit_racket)

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
    sysid.add_argument("--out", default=str(MODELS_DIR / "joint_dynamics_identified.yaml"))
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
    cameras.add_argument("--output", default=str(MODELS_DIR / "cameras.yaml"), help="calibration file to write")
    cameras.add_argument("--plot", default="", help="coverage plot (default: <output>_coverage.png)")
    cameras.add_argument("--json", action="store_true")
    cameras.set_defaults(run=cmd_cameras)

    graphs = commands.add_parser("diagrams", help="render every diagram's graph into diagrams/")
    graphs.add_argument("--out", default=str(REPO_ROOT / "diagrams"))
    graphs.set_defaults(run=cmd_diagrams)

    serves = commands.add_parser("serves", help="the serve library: `serves search` (GA, robot plans, noisy repeats), `serves evaluate` and "
                                                "`serves replan` (re-made on the current robot from its genes)")
    serves.add_argument("action", choices=("search", "evaluate", "replan"))
    serves.add_argument("--library", default=str(MODELS_DIR / "serve_library.npz"), help="evaluate, replan: the library (default: %(default)s)")
    serves.add_argument("--kinds", default="short_backspin,long_topspin,long_sidespin,fast_long,long_backspin", help="search: serve kinds, comma-separated (default: %(default)s)")
    serves.add_argument("--seeds", default="0-3", help="search: GA seeds, comma-separated integers or ranges (default: %(default)s)")
    serves.add_argument("--generations", type=int, default=100, help="search: GA generations at most (the authors': %(default)s)")
    serves.add_argument("--repeats", type=int, help=f"noisy executions of each serve on the diagram (default: {SERVE_REPEATS}; replan: the library's own)")
    serves.add_argument("--seed", type=int, help="the executions' noise and ball perturbations (default: 0; replan: the library's own)")
    serves.add_argument("--batch", type=int, default=32, help="executions played at once on the segment-stepped diagram (default: %(default)s)")
    serves.add_argument("--out", default=str(MODELS_DIR / "serve_library.npz"), help="search, replan: the library to write (+ .json sidecar; default: %(default)s)")
    serves.add_argument("--extend", help="search: keep this library's serves and add the new ones (it may be --out)")
    serves.add_argument("--executed", action="store_true", help="search: the GA scores the strikes the robot makes (its planning in the fitness, the paper's; ~25 x slower) instead of the ball-level ones")
    serves.add_argument("--json", action="store_true")
    serves.set_defaults(run=cmd_serves)

    results = commands.add_parser("results", help="regenerate the README's results table from the sidecars and stored JSON")
    results.add_argument("--check", action="store_true", help="only check: exit 1 if README.md or docs/benchmarks.md is stale")
    results.set_defaults(run=cmd_results)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Runs ``ace-drake`` with ``argv`` (default: the process's arguments); returns the exit code."""
    artefacts.record_command_line(sys.argv[1:] if argv is None else argv)  # for the sidecars' provenance
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (InputError, FileNotFoundError) as error:  # bad input (ConfigError, MatchDataError, ... are InputErrors); a bug keeps its traceback
        log(f"ace-drake {args.command}: error: {error}")
        return 2


if __name__ == "__main__":
    sys.exit(main())
