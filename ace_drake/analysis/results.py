"""The headline results: one table generated from the files the figures live in (``ace-drake results``).

Sources, all relative to the repository root:

- the shipped policies' sidecars ``models/policies/<name>.json`` (``SHIPPED_POLICIES``, the one
  list of what ships: the tests hold ``models/policies/`` and ``models/train_<name>.yaml`` to it): the
  export evaluation ``final_evaluation`` that ``ace-drake train --evaluate-data`` records (the
  recorded human shots through the cameras: as ``ace-drake evaluate`` plays them, or, exported
  before that, on the continuous-time diagram at the run's seed);
- the fitted ball model's sidecar ``models/ball_physics_fitted.json`` (``ace-drake physics-fit``)
  and the fitted racket model's ``models/racket_fitted.json`` (``ace-drake physics-fit-racket``);
- stored evaluations ``docs/results/<controller>.json`` (``ace-drake evaluate ... --json``
  redirected there; the default controller's row says "not measured" until its file exists);
- stored benchmarks ``docs/benchmarks/<name>.json`` (``ace-drake bench <name> --json``);
- stored held-out evaluations ``docs/results/heldout/<controller>.json`` (``evaluation.heldout``:
  they choose the main job's controller);
- stored matches ``docs/results/matches/<opponent>.json`` (``ace-drake rally --opponent ...
  --matches N --json`` redirected there), set beside the paper's Fig. 3a (``PAPER_MATCHES``).

``render_results`` turns them into the README's table, ``render_benchmarks`` into the table of
docs/benchmarks.md; ``replace_block`` puts a table between its markers and ``stale_files`` says
which document no longer shows what its sources hold. No figure in either table is typed by hand.
Plain Python: no Drake, no torch.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from ace_drake.contracts import DEFAULT_CONTROLLER  # the row the table starts with
from ace_drake.evaluation.heldout import choose_controller, heldout_evaluations

POLICY_ROLES = {  # the shipped policies, each with what its row says it is
    "rally_hit_state_braking": "best policy (hit-state actor)",
    "rally_paper_mc": "the paper's action (eq. 12), SAC at scale",
    "rally_skill": "follows the skill's aim and spin",
}
SHIPPED_POLICIES = tuple(sorted(POLICY_ROLES))
RESULTS_BEGIN, RESULTS_END = "<!-- results:begin -->", "<!-- results:end -->"
BENCHMARKS_BEGIN, BENCHMARKS_END = "<!-- benchmarks:begin -->", "<!-- benchmarks:end -->"
README = "README.md"
BENCHMARKS_PAGE = "docs/benchmarks.md"
EVALUATE_COMMAND = "ace-drake evaluate --controller {controller} --data ../shared/data/ace_match_events_elite.csv --json"
BENCHMARK_COMMANDS = {"sim": "ace-drake bench sim --json", "train": "ace-drake bench train --json"}  # what made a stored bench JSON that does not record its command
NOT_MEASURED = "not measured"
# The paper's matches (main text, Fig. 3a, and the rally length of its *Results*): against five elite players.
PAPER_MATCHES = "paper (Fig. 3a, real robot against 5 elite players, golden point): 3 of 5 matches, 7 of 13 games; rally length 5.0 +- 3.0 shots"


@dataclasses.dataclass(frozen=True)
class Row:
    """One line of the results table: what was measured, the figure, on what, and from which file."""

    what: str
    figure: str
    measured_on: str
    source: str


def read_json(path: Path) -> dict | None:
    """The JSON object in ``path``, or None if there is no such file."""
    return json.loads(path.read_text()) if path.is_file() else None


def percent(value: float) -> str:
    return f"{100.0 * value:.1f}%"


def return_rate_text(rate: dict) -> str:
    """'88.2% (360 of 408 playable; 95% CI 84.7-91.0%)' from an evaluation's ``return_rate``."""
    low, high = rate["ci95"]
    return f"{percent(rate['rate'])} ({rate['returned']} of {rate['played']} playable; 95% CI {100 * low:.1f}-{100 * high:.1f}%)"


def _source(path: str) -> str:
    """The source file (the sidecars record the command that wrote them; docs/benchmarks.md the rest)."""
    return f"`{path}`"


def _shots_text(evaluation: dict) -> str:
    """'637 recorded shots of ace_match_events_elite.csv, cameras' from an evaluation's keys."""
    data = evaluation.get("data")
    shots = f"{evaluation['episodes']} recorded human shots of {Path(data).name}" if data else f"{evaluation['episodes']} synthetic shots"
    return f"{shots}, {evaluation['sensors']}"


def _seed_text(evaluation: dict) -> str:
    """'seed 0', or for an ``evaluate --repeats 5`` 'seeds 0-4, each shot 5 times'."""
    seed, repeats = evaluation["seed"], evaluation.get("repeats", 1)
    return f"seed {seed}" if repeats == 1 else f"seeds {seed}-{seed + repeats - 1}, each shot {repeats} times"


def policy_row(name: str, sidecar: dict | None, source: str) -> Row:
    """The export evaluation of a shipped policy's sidecar (``final_evaluation``)."""
    what = f"`policy:{name}`: {POLICY_ROLES[name]}"
    evaluation = None if sidecar is None else sidecar.get("final_evaluation")
    if evaluation is None:
        return Row(what, NOT_MEASURED, "-", _source(source))
    figure = return_rate_text(evaluation["return_rate"])
    held_out = evaluation.get("held_out")
    if held_out:
        figure += f"; held-out players ({', '.join(held_out['players'])}): {return_rate_text(held_out['return_rate'])}"
    if "seed" in evaluation:  # as `ace-drake evaluate` measures it (training.export.final_evaluation)
        measured_on = f"{_shots_text(evaluation)}, seed {evaluation['seed']}, {_diagram_text(evaluation)}, {sidecar['date']}"
    else:  # exported before: the continuous-time diagram at the run's seed
        measured_on = f"{_shots_text(evaluation)}, seed {sidecar['seed']} (the run's), {sidecar['date']}"
    return Row(what, figure, measured_on, _source(source))


def _diagram_text(evaluation: dict) -> str:
    """'the segment diagram, 32 at a time' from an evaluation's keys (continuous if it has none)."""
    batch = f", {evaluation['batch']} at a time" if evaluation.get("batch", 1) > 1 else ""
    return f"the {evaluation.get('stepping', 'continuous')} diagram{batch}"


def evaluation_row(controller: str, evaluation: dict | None, source: str) -> Row:
    """A stored ``ace-drake evaluate --json`` (or "not measured" without one)."""
    what = f"`{controller}`" + (": the default controller" if controller == DEFAULT_CONTROLLER else "")
    if evaluation is not None and evaluation.get("ball_params"):
        what += f", ball model `{Path(evaluation['ball_params']).name}`"
    if evaluation is None:
        command = EVALUATE_COMMAND.format(controller=controller)
        return Row(what, NOT_MEASURED, f"`{command} > {source}` measures it on the recorded human shots", _source(source))
    figure = return_rate_text(evaluation["return_rate"])
    measured_on = (f"{_shots_text(evaluation)}, {_seed_text(evaluation)}, {_diagram_text(evaluation)}"
                   + (f", {evaluation['date']}" if evaluation.get("date") else ""))
    return Row(what, figure, measured_on, _source(source))


def racket_fit_row(sidecar: dict | None, source: str) -> Row:
    """The racket contact model fitted to measured contacts against the paper's, on the held-out
    games (physics-fit-racket sidecar)."""
    what = "racket contact model fitted to measured contacts (`models/racket_fitted.yaml`, with its residual network)"
    if sidecar is None:
        return Row(what, NOT_MEASURED, "-", _source(source))
    held_out = sidecar["figures"]["held_out"]
    cells = []
    for label, name in (("paper", "default"), (f"fitted {sidecar['law']} law", f"fitted_{sidecar['law']}"), ("with residual", "fitted_residual")):
        velocity, spin = held_out[name]["velocity_error_m_s"], held_out[name]["spin_error_rad_s"]
        cells.append(f"{label} {velocity['median']:.2f} m/s (rms {velocity['rms']:.2f}), {spin['median']:.1f} rad/s (rms {spin['rms']:.1f})")
    split = sidecar["split"]
    measured_on = (f"post-contact velocity and spin error, median, on {split['held_out_contacts']} contacts of "
                   f"{len(split['held_out_games'])} held-out games; fitted on {split['training_contacts']}, "
                   f"{sidecar['data']['file']}, {sidecar['date']}")
    return Row(what, "; ".join(cells), measured_on, _source(source))


def ball_fit_row(sidecar: dict | None, source: str) -> Row:
    """The fitted ball model against the paper's on the held-out players (physics-fit sidecar)."""
    what = "ball model fitted to the recorded matches (`models/ball_physics_fitted.yaml`)"
    if sidecar is None:
        return Row(what, NOT_MEASURED, "-", _source(source))
    held_out = sidecar["figures"]["held_out_players"]
    fitted, paper = held_out["fitted"]["landing_error_m"], held_out["initial"]["landing_error_m"]
    figure = (f"landing error median {100 * fitted['median']:.1f} cm (p90 {100 * fitted['p90']:.1f}), "
              f"paper model {100 * paper['median']:.1f} cm (p90 {100 * paper['p90']:.1f})")
    fit_pairs = sidecar["figures"]["fit_players"]["fitted"]["pairs"]
    measured_on = (f"{held_out['fitted']['pairs']} (shot or bounce) -> bounce pairs of {', '.join(sidecar['held_out_players'])}, "
                   f"held out; fitted on {', '.join(sidecar['fit_players'])} ({fit_pairs} pairs), {sidecar['date']}")
    return Row(what, figure, measured_on, _source(source))


def heldout_row(root: Path) -> list[Row]:
    """The controllers measured on the held-out players (``evaluation.heldout``), best first, and
    the one ``ace-drake rally`` plays; none when nothing is stored."""
    directory = root / "docs/results/heldout"
    evaluations = heldout_evaluations(directory)
    if not evaluations:
        return []
    available = {"returner", "still", *(f"policy:{path.stem}" for path in (root / "models/policies").glob("*.pt"))}
    chosen, _ = choose_controller(evaluations, available)
    ranked = sorted(evaluations.items(), key=lambda item: -(item[1]["return_rate"]["rate"] or 0.0))
    figure = "; ".join(f"`{name}` {return_rate_text(evaluation['return_rate'])}" for name, evaluation in ranked)
    some = ranked[0][1]
    what = f"the main job's controller, chosen on the held-out players: `{chosen}`"
    measured_on = f"all recorded shots of {', '.join(some['players'])}, {some['sensors']}, {_seed_text(some)}, the {some.get('stepping', 'segment')} diagram"
    return [Row(what, figure, measured_on, "`docs/results/heldout/`")]


def match_row(result: dict, source: str) -> Row:
    """A stored ``ace-drake rally --json``: matches, games and points won, rally length, and how
    often the simulated human's returns landed against how often the recorded player's did."""
    match, recorded = result["match"], result["opponent_recorded"]
    what = f"`{result['controller']}` against {result['opponent']}'s model"
    games = len(match["games"])
    figure = (f"won {match['matches_won']} of {match['matches']} matches, {match['games_won']} of {games} games, "
              f"{match['points_won']} of {match['points_played']} points; rally length {match['rally_length_mean']:.1f} +- "
              f"{match['rally_length_std']:.1f} strikes; the robot's returns in play {percent(1 - match['robot_return_errors'] / max(match['robot_returns'], 1))}, "
              f"the human's {percent(1 - match['human_return_errors'] / max(match['human_returns'], 1))} (recorded {percent(recorded['returns_landed'])}); "
              f"service faults: the robot's {match['service_faults']} of {match['points_served']}, the human's {match['human_service_faults']} of {match['human_points_served']}")
    rules = f"best of {result['best_of']}" + (", golden point" if result["golden_point"] else "")
    measured_on = f"{match['matches']} matches ({rules}), {result['sensors']}, seed {result['seed']}" + (f", {result['date']}" if result.get("date") else "")
    return Row(what, figure, measured_on, _source(source))


def match_rows(root: Path) -> list[Row]:
    """One row per stored match result (``docs/results/matches/*.json``), then the paper's."""
    paths = sorted((root / "docs/results/matches").glob("*.json"))
    if not paths:
        return []
    return [match_row(read_json(path), f"docs/results/matches/{path.name}") for path in paths] + [Row("the paper's matches", PAPER_MATCHES, "-", "the paper")]


def speed_rows(sim: dict | None, source: str) -> list[Row]:
    """Real-time factors of the rally diagram and its ceilings, and RallyEnv steps/s (bench sim)."""
    if sim is None:
        return [Row("rally diagram speed", NOT_MEASURED, "-", _source(source))]
    setup = f"ready-pose controller, median of {sim['episodes']} episodes of {sim['simulated_seconds_per_episode']:g} s from synthetic shots"
    rows = [
        Row(f"rally diagram speed, {sim[key]['sensors']}",
            f"{sim[key]['real_time_factor_median']:.2f} x real time ({sim[key]['cpu_real_time_factor_median']:.2f} per CPU second)",
            setup, _source(source))
        for key in ("rally_cameras", "rally_statistical")
    ]
    ceilings = sim["ceilings"]
    rows.append(Row("ceilings of any rally diagram: the ball alone, the robot alone under its control stack",
                    f"{ceilings['ball_alone_cpu_real_time_factor_median']:.1f} x and "
                    f"{ceilings['controlled_robot_alone_cpu_real_time_factor_median']:.1f} x real time per CPU second",
                    "the same shots and seconds", _source(source)))
    rows.append(Row("training environment (RallyEnv) speed", f"{sim['env']['steps_per_second']:.1f} steps per second",
                    f"{sim['env']['actions']} actions, statistical sensors", _source(source)))
    if "rally_cameras_b1" in sim:
        b1 = sim["rally_cameras_b1"]
        rows.append(Row(f"segment-stepped rally diagram speed (B = 1), {b1['sensors']}", f"{b1['real_time_factor_median']:.1f} x real time",
                        f"as above; x {sim['ratio_cameras_b1_new_to_old']:.1f} the continuous-time diagram's", _source(source)))
        best = max(sim["segment_env"].items(), key=lambda item: item[1]["steps_per_second"])
        rows.append(Row("batched training environment (RallyVectorEnv) speed", f"{best[1]['steps_per_second']:.0f} steps per second at B = {best[0]}",
                        f"one process, x {sim['ratio_env_steps_new_to_old']:.1f} RallyEnv's", _source(source)))
    return rows


def collection_rows(train: dict | None, source: str) -> list[Row]:
    """Training collection with two Ray workers and the learner's updates/s (bench train); none
    when it was not measured."""
    if train is None or not train.get("vector_env_steps_per_s"):
        return []
    best = max(train["vector_env_steps_per_s"].items(), key=lambda item: item[1])
    updates = max(train["updates_per_s"].values())
    return [
        Row("training collection, 2 Ray workers", f"{best[1]:.0f} steps per second (B = {best[0]} each); RallyEnv: {train['env_steps_per_s']['2']:.0f}",
            f"the freshly initialised actor, statistical sensors, full control stack, {train['seconds_per_collection']:g} s, {train['date']}", _source(source)),
        Row("learner (SAC) updates", f"{updates:.0f} per second (batch {train['batch_size']})", "on the collected episodes, the better of 1 and 2 torch threads", _source(source)),
    ]


def result_rows(root: Path) -> list[Row]:
    """Every row of the README's table, read from the files under ``root``."""
    rows = [evaluation_row(DEFAULT_CONTROLLER, read_json(root / "docs/results" / f"{DEFAULT_CONTROLLER}.json"),
                           f"docs/results/{DEFAULT_CONTROLLER}.json")]
    for path in sorted((root / "docs/results").glob("*.json")):
        if path.stem != DEFAULT_CONTROLLER:
            evaluation = read_json(path)
            rows.append(evaluation_row(evaluation.get("controller", path.stem), evaluation, f"docs/results/{path.name}"))
    for name in SHIPPED_POLICIES:
        source = f"models/policies/{name}.json"
        rows.append(policy_row(name, read_json(root / source), source))
    rows.extend(heldout_row(root))
    rows.append(ball_fit_row(read_json(root / "models/ball_physics_fitted.json"), "models/ball_physics_fitted.json"))
    rows.append(racket_fit_row(read_json(root / "models/racket_fitted.json"), "models/racket_fitted.json"))
    rows.extend(match_rows(root))
    rows.extend(speed_rows(read_json(root / "docs/benchmarks/sim.json"), "docs/benchmarks/sim.json"))
    rows.extend(collection_rows(read_json(root / "docs/benchmarks/train.json"), "docs/benchmarks/train.json"))
    return rows


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def render_table(header: tuple[str, ...], rows: list[tuple[str, ...]]) -> str:
    """A markdown table."""
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join("---" for _ in header) + " |"]
    lines += ["| " + " | ".join(_cell(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def render_results(root: Path) -> str:
    """The README's results table (between ``RESULTS_BEGIN`` and ``RESULTS_END``)."""
    rows = result_rows(root)
    return render_table(("what", "figure", "measured on", "source"), [dataclasses.astuple(row) for row in rows])


def render_benchmarks(root: Path) -> str:
    """docs/benchmarks.md's generated part: every stored ``docs/benchmarks/<name>.json`` in full."""
    parts = []
    sim = read_json(root / "docs/benchmarks/sim.json")
    if sim is not None:
        rows = [(sim[key]["sensors"], f"{sim[key]['real_time_factor_median']:.2f}", f"{sim[key]['real_time_factor_min']:.2f}",
                 f"{sim[key]['cpu_real_time_factor_median']:.2f}", f"{sim[key]['wall_seconds_median']:.3f}")
                for key in ("rally_cameras", "rally_statistical", "rally_statistical_no_hit_prediction")]
        parts.append(f"`docs/benchmarks/sim.json` (`{BENCHMARK_COMMANDS['sim']}`; controller: {sim['controller']}; "
                     f"{sim['episodes']} episodes of {sim['simulated_seconds_per_episode']:g} simulated s after a warm-up):")
        parts.append(render_table(("rally diagram", "x real time, median", "min", "per CPU second, median", "wall s, median"), rows))
        ceilings, env = sim["ceilings"], sim["env"]
        parts.append(render_table(("what", "figure"), [
            ("the ball alone (BallPlant in a Simulator), per CPU second", f"{ceilings['ball_alone_cpu_real_time_factor_median']:.1f} x real time"),
            ("the robot alone under its control stack, per CPU second", f"{ceilings['controlled_robot_alone_cpu_real_time_factor_median']:.1f} x real time"),
            ("statistical sensor against cameras", f"x {sim['ratio_statistical_to_cameras']:.2f}"),
            ("without the hit prediction against with it", f"x {sim['ratio_no_hit_prediction_to_statistical']:.2f}"),
            (f"RallyEnv, {env['actions']} actions", f"{env['steps_per_second']:.1f} steps/s, {env['episode_steps_median']:g} steps per episode (median)"),
        ]))
        if "segment_env" in sim:
            rows = [(sim[f"rally_{path}_b1"]["sensors"], f"{sim[f'rally_{path}_b1']['real_time_factor_median']:.1f}",
                     f"{sim[f'rally_{path}_b1']['real_time_factor_min']:.1f}") for path in ("cameras", "statistical")]
            parts.append(f"The segment-stepped diagram (B = 1), the same controller and shots (cameras: x {sim['ratio_cameras_b1_new_to_old']:.1f} the continuous-time diagram):")
            parts.append(render_table(("segment-stepped rally diagram", "x real time, median", "min"), rows))
            rows = [(batch, f"{row['steps_per_second']:.0f}", f"{row['steps_per_cpu_second']:.0f}", f"{row['resident_memory_mb']:.0f}")
                    for batch, row in sim["segment_env"].items()]
            parts.append(f"RallyVectorEnv, {env['actions']} actions, one process (best: x {sim['ratio_env_steps_new_to_old']:.1f} RallyEnv's steps/s):")
            parts.append(render_table(("B", "steps/s", "steps per CPU s", "resident MB"), rows))
        profile = sim.get("profile", {})
        if profile:
            paths = [path for path in profile]
            def largest_share(name: str) -> float:
                return max(profile[path]["systems"].get(name, {"share": 0.0})["share"] for path in paths)

            names = {name for path in paths for name in profile[path]["systems"]}
            systems = sorted((name for name in names if largest_share(name) >= 0.001), key=lambda name: -largest_share(name))
            rows = [(f"`{name}`", *(percent(profile[path]["systems"][name]["share"]) if name in profile[path]["systems"] else "-" for path in paths))
                    for name in systems]
            rows.append(("outside the systems (Drake's dispatch, integrator, the benchmark)",
                         *(percent(profile[path]["outside_systems_share"]) for path in paths)))
            parts.append("Where the time goes (share of the profiled wall time; tracing slows Python more than C++):")
            parts.append(render_table(("system", *(f"{path}" for path in paths)), rows))
    train = read_json(root / "docs/benchmarks/train.json")
    if train is not None:
        rows = [(f"RallyEnv, {workers} worker(s)", f"{rate:.0f}") for workers, rate in train["env_steps_per_s"].items()]
        rows += [(f"RallyVectorEnv B = {batch}, 2 workers", f"{rate:.0f}") for batch, rate in train.get("vector_env_steps_per_s", {}).items()]
        parts.append(f"`docs/benchmarks/train.json` (`{train.get('command', BENCHMARK_COMMANDS['train'])}`; Ray workers, {train['seconds_per_collection']:g} s of collection each):")
        parts.append(render_table(("collection", "environment steps/s"), rows))
        updates = ", ".join(f"{rate:.1f} with {threads} torch thread(s)" for threads, rate in train["updates_per_s"].items())
        ratio = train.get("ratio_env_steps_new_to_old")
        parts.append(f"Learner: {updates} (batch {train['batch_size']}); updates per environment step at the best collection: "
                     f"{train['updates_per_env_step']:.3f}" + (f"; best vector collection x {ratio:.1f} RallyEnv's." if ratio else "."))
    return "\n\n".join(parts) if parts else NOT_MEASURED


def replace_block(text: str, block: str, begin: str = RESULTS_BEGIN, end: str = RESULTS_END) -> str:
    """``text`` with everything between the markers ``begin`` and ``end`` replaced by ``block``."""
    start, stop = text.find(begin), text.find(end)
    if start < 0 or stop < start:
        raise ValueError(f"no '{begin}' ... '{end}' block in the text")
    return text[: start + len(begin)] + "\n" + block + "\n" + text[stop:]


def generated_documents(root: Path) -> dict[str, str]:
    """Each generated document (path relative to ``root``) as it should read now."""
    documents = {}
    for name, render, begin, end in ((README, render_results, RESULTS_BEGIN, RESULTS_END),
                                     (BENCHMARKS_PAGE, render_benchmarks, BENCHMARKS_BEGIN, BENCHMARKS_END)):
        path = root / name
        if path.is_file():
            documents[name] = replace_block(path.read_text(), render(root), begin, end)
    return documents


def stale_files(root: Path) -> list[str]:
    """The generated documents under ``root`` whose tables differ from what their sources give."""
    return [name for name, text in generated_documents(root).items() if (root / name).read_text() != text]


def update_files(root: Path) -> list[str]:
    """Rewrites the stale generated documents under ``root``; returns their names."""
    stale = stale_files(root)
    for name, text in generated_documents(root).items():
        if name in stale:
            (root / name).write_text(text)
    return stale
