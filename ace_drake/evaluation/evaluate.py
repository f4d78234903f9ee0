"""Return-rate evaluation of a rally controller (paper, Fig. 3c-g), one episode per incoming shot.

Each shot (a ball state just after the opponent's hit) is played on the rally diagram with the
controller driving the robot through the full control stack and the robot perceiving the ball
through its sensors. The figures: the return rate with its 95% Wilson interval, overall
and binned by the shot's speed and spin (Fig. 3c-d); the distributions of the returns' outgoing
speed and spin (Fig. 3e-f); the time from the bounce on the robot's half to the hit (Fig. 3g);
and every episode that was not returned counted by its reason. Shots that were not playable (they
did not bounce legally on the robot's half under the simulated physics: ``Outcome.INVALID``) are
counted and left out of the rate.

The seed (the noise of the sensors and of the ball's perturbations) moves a controller's rate on
the same shots by several points (docs/robot_and_control.md). ``evaluate_controller(repeats=n)``
plays every shot n times, with seeds seed, seed + 1, ...; its figures pool all the episodes, and
its intervals are Wilson's over the effective number of episodes (``clustered_return_rate``),
since the repeats of one shot are not independent trials.

Each episode is played with a skill [y_desired (m), w_p, w_s] (paper, *States*, *Rewards*): the
diagram's default (the centre line, w_p = 1, w_s = 0) or one per shot. ``skill_figures`` says
how the returns followed it: where they landed against y_desired (the aim), their topspin at
landing by the sign of w_s, and the mean eq. (10) reward.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Sequence

import numpy as np

from ace_drake.artefacts import provenance, sha256
from ace_drake.config import ConfigError
from ace_drake.contracts import Outcome
from ace_drake.control.params import RallyParams
from ace_drake.diagrams import build_rally_diagram, build_segment_rally_diagram
from ace_drake.evaluation.controllers import NoisyActions, diagram_params_for, hit_state_controller, make_controller, rally_params
from ace_drake.evaluation.runner import Episode, RallyRunner, SegmentRallyRunner
from ace_drake.learning.params import RewardParams
from ace_drake.learning.rewards import terminal_reward, travel_frame_spin
from ace_drake.play.params import ShotParams
from ace_drake.play.shots import human_shots, make_distribution

SPEED_BINS = (0.0, 6.0, 8.0, 10.0, 12.0, 14.0, np.inf)  # m/s, the shot's speed just after the hit
SPIN_BINS = (0.0, 100.0, 200.0, 300.0, 400.0, np.inf)  # rad/s, its spin rate
# The skill's w_s in three groups: backspin asked for (w_s < -1/3), neither, topspin (w_s > 1/3).
SPIN_SKILL_GROUPS = (("backspin", -1.0, -1.0 / 3.0), ("neutral", -1.0 / 3.0, 1.0 / 3.0), ("topspin", 1.0 / 3.0, 1.0))


def return_rate(returned: int, played: int) -> dict:
    """The fraction returned with its 95% Wilson score interval (None without episodes)."""
    if played == 0:
        return {"returned": 0, "played": 0, "rate": None, "ci95": None}
    return {"returned": returned, "played": played, "rate": returned / played, "ci95": list(wilson_interval(returned / played, played))}


def _distribution(values) -> dict | None:
    """Median, 10th and 90th percentiles and the count of ``values`` (None when empty)."""
    values = np.asarray(values, dtype=float)
    if values.size == 0:
        return None
    p10, median, p90 = np.percentile(values, [10, 50, 90])
    return {"count": int(values.size), "p10": p10, "median": median, "p90": p90}


def clustered_return_rate(returned: np.ndarray, shot: np.ndarray) -> dict:
    """The fraction of ``returned`` (n,) episodes, played on shots ``shot`` (n,) (an index each; a
    shot's repeats share it), with a 95% Wilson interval over the effective number of episodes
    n / deff: deff is the design effect of playing each shot several times (Kish), the variance
    of the rate as a ratio estimator over the shots against a binomial's over n episodes, kept
    between 1 (repeats as informative as new shots) and n / shots (a repeat adds nothing; also
    when every episode agrees, where the variances vanish). The ``return_rate`` dict's keys; for
    repeated evaluations, whose episodes of one shot are not independent trials."""
    returned = np.asarray(returned, dtype=bool)
    n = returned.size
    if n == 0:
        return return_rate(0, 0)
    _, index = np.unique(np.asarray(shot), return_inverse=True)
    hits = np.bincount(index, weights=returned).astype(float)
    plays = np.bincount(index).astype(float)
    shots, rate = len(plays), float(returned.mean())
    most = n / shots  # the mean repeats of a shot
    binomial = rate * (1.0 - rate) / n
    if shots > 1 and binomial > 0.0:
        clustered = shots / (shots - 1) * np.sum((hits - rate * plays) ** 2) / n**2
        deff = float(np.clip(clustered / binomial, 1.0, most))
    else:
        deff = most
    return {"returned": int(returned.sum()), "played": n, "rate": rate, "ci95": list(wilson_interval(rate, n / deff))}


def wilson_interval(rate: float, n: float, z: float = 1.959963984540054) -> tuple[float, float]:
    """The Wilson score interval (95% for the default z) of a proportion ``rate`` over ``n``
    trials, ``n`` possibly fractional (an effective number)."""
    centre = (rate + z * z / (2.0 * n)) / (1.0 + z * z / n)
    half = z / (1.0 + z * z / n) * np.sqrt(rate * (1.0 - rate) / n + z * z / (4.0 * n * n))
    return max(0.0, float(centre - half)), min(1.0, float(centre + half))


def _binned(values: np.ndarray, returned: np.ndarray, edges, shot: np.ndarray | None = None) -> list[dict]:
    rows = []
    for low, high in zip(edges[:-1], edges[1:]):
        inside = (values >= low) & (values < high)
        rate = return_rate(int(returned[inside].sum()), int(inside.sum())) if shot is None else clustered_return_rate(returned[inside], shot[inside])
        rows.append({"low": low, "high": None if np.isinf(high) else high, **rate})
    return rows


def summarize(episodes: list[Episode], shot_count: int | None = None) -> dict:
    """The evaluation figures (module docstring) of finished episodes. ``shot_count``: for a
    repeated evaluation, the number of distinct shots, episode i having played shot i mod
    ``shot_count``; its intervals are then ``clustered_return_rate``'s, else Wilson's."""
    outcomes = [episode.result.outcome for episode in episodes]
    playable_index = np.array([i for i, outcome in enumerate(outcomes) if outcome is not Outcome.INVALID], dtype=int)
    playable = [episodes[i] for i in playable_index]
    shot = None if shot_count is None else playable_index % shot_count
    returned = np.array([episode.result.outcome is Outcome.RETURNED for episode in playable], dtype=bool)
    shots = np.array([episode.shot for episode in playable]).reshape(-1, 9)
    hits = [episode.result.hit for episode in playable if episode.result.outcome is Outcome.RETURNED]
    reasons = Counter(
        f"{episode.result.outcome.value}: {episode.result.reason}" for episode in playable if episode.result.outcome is not Outcome.RETURNED
    )
    bounce_to_hit = [e.result.bounce_to_hit_time for e in playable if e.result.bounce_to_hit_time is not None]
    return {
        "episodes": len(episodes),
        "invalid_shots": len(episodes) - len(playable),
        "return_rate": return_rate(int(returned.sum()), len(playable)) if shot is None else clustered_return_rate(returned, shot),
        "by_incoming_speed": _binned(np.linalg.norm(shots[:, 3:6], axis=1), returned, SPEED_BINS, shot),
        "by_incoming_spin": _binned(np.linalg.norm(shots[:, 6:9], axis=1), returned, SPIN_BINS, shot),
        "outgoing_speed_m_s": _distribution([np.linalg.norm(hit.state_post[3:6]) for hit in hits]),
        "outgoing_spin_rad_s": _distribution([np.linalg.norm(hit.state_post[6:9]) for hit in hits]),
        "bounce_to_hit_s": _distribution(bounce_to_hit),
        "not_returned_by_reason": dict(reasons.most_common()),
        "segments_accepted": int(sum(e.segments[0] for e in episodes)),
        "segments_refused": int(sum(e.segments[1] for e in episodes)),
        "skill": skill_figures(episodes),
    }


def skill_figures(episodes: list[Episode], reward: RewardParams | None = None) -> dict:
    """How the playable episodes followed their skills [y_desired (m), w_p, w_s]:

    - ``aim``, over the returns whose skill weighs the position (w_p > 0): the landing's distance
      |y_land - y_desired| (m; median, p10, p90) and, when y_desired varies (std > 5 cm), the
      least-squares slope and the correlation of y_land on y_desired (1 and 1 for perfect aim;
      0 for a controller that ignores it);
    - ``landing_topspin_rad_s``, per group of w_s (``SPIN_SKILL_GROUPS``): the returns' spin about
      the travel frame's y axis at landing (``rewards.travel_frame_spin``; > 0 topspin);
    - ``mean_reward``: the eq. (10) terminal reward (``rewards.terminal_reward`` with ``reward``,
      default ``RewardParams()``) averaged over the playable episodes."""
    reward = reward or RewardParams()
    playable = [e for e in episodes if e.result.outcome is not Outcome.INVALID]
    returns = [e for e in playable if e.result.outcome is Outcome.RETURNED]
    aimed = [e for e in returns if e.skill[1] > 0.0]
    y_desired = np.array([e.skill[0] for e in aimed])
    y_land = np.array([e.result.landing.state_pre[1] for e in aimed])
    aim = {"count": len(aimed), "error_m": _distribution(np.abs(y_land - y_desired)), "slope": None, "correlation": None}
    if len(aimed) > 2 and np.std(y_desired) > 0.05:
        aim["slope"] = float(np.polyfit(y_desired, y_land, 1)[0])
        aim["correlation"] = float(np.corrcoef(y_desired, y_land)[0, 1])
    spin = []
    w_s = np.array([e.skill[2] for e in returns])
    groups = 1 + (w_s > SPIN_SKILL_GROUPS[2][1]).astype(int) - (w_s < SPIN_SKILL_GROUPS[0][2]).astype(int)
    for index, (name, low, high) in enumerate(SPIN_SKILL_GROUPS):
        landing = [travel_frame_spin(e.result.landing.state_pre) for e, group in zip(returns, groups) if group == index]
        spin.append({"group": name, "w_s_low": low, "w_s_high": high, "landing_topspin_rad_s": _distribution(landing)})
    rewards = [terminal_reward(e.result, e.skill, reward) for e in playable]
    return {"aim": aim, "landing_topspin_rad_s": spin, "mean_reward": float(np.mean(rewards)) if rewards else None}


def run_episodes(
    runner: RallyRunner,
    shots: np.ndarray,
    serve: np.ndarray,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    skills: np.ndarray | None = None,
) -> list[Episode]:
    """Plays every shot (n, 9) once (``serve`` (n,) marks serves), episode i seeded with
    ``seed * 1_000_003 + i`` and played with skill ``skills[i]`` ((n, 3) [y_desired (m), w_p,
    w_s]; None: the diagram's default); reports progress every 10% when ``progress`` is given."""
    shots = np.asarray(shots, dtype=float).reshape(-1, 9)
    if skills is not None:
        skills = np.asarray(skills, dtype=float)
        if skills.shape != (len(shots), 3):
            raise ValueError(f"run_episodes: skills must be ({len(shots)}, 3), one per shot, got {skills.shape}")
    episodes = []
    start = time.perf_counter()
    for index, (shot, is_serve) in enumerate(zip(shots, serve)):
        skill = None if skills is None else skills[index]
        episodes.append(runner.run(shot, seed=seed * 1_000_003 + index, serve=bool(is_serve), skill=skill))
        if progress is not None and ((index + 1) % max(1, len(shots) // 10) == 0 or index + 1 == len(shots)):
            rate = np.mean([e.result.outcome is Outcome.RETURNED for e in episodes])
            progress(f"evaluate: {index + 1}/{len(shots)} episodes, returned {rate:.0%} so far, {time.perf_counter() - start:.0f} s")
    return episodes


def evaluate(controller, params: RallyParams, shots: np.ndarray, serve: np.ndarray, seed: int = 0, progress=None,
             skills: np.ndarray | None = None, batch: int = 1) -> dict:
    """``play``'s episodes summarized (``summarize``), with the wall time (s), the stepping and
    the batch."""
    start = time.perf_counter()
    episodes = play(controller, params, shots, serve, seed, progress, skills, batch)
    return {**summarize(episodes), "wall_time_s": time.perf_counter() - start, "stepping": params.stepping, "batch": batch}


def play(controller, params: RallyParams, shots: np.ndarray, serve: np.ndarray, seed: int = 0, progress=None,
         skills: np.ndarray | None = None, batch: int = 1) -> list[Episode]:
    """Plays ``controller`` (a policy callable or torch module; for a batch of a stateful
    controller, a sequence of ``batch`` of them, one per environment) on ``shots`` with the rally
    diagram of ``params`` (without the observation's hit prediction when the controller does not
    read it: ``evaluation.controllers.diagram_params_for``), each shot with its skill of ``skills``
    and shot i seeded ``seed * 1_000_003 + i``: on the continuous-time diagram one episode after
    another (``run_episodes``), on the segment-stepped one (``params.stepping``) ``batch`` at a
    time (``SegmentRallyRunner``). Returns the episodes, in the order of ``shots``."""
    controllers = list(controller) if isinstance(controller, (list, tuple)) else [controller]
    controllers = [hit_state_controller(c, params) for c in controllers]
    params = diagram_params_for(controllers[0], params)
    start = time.perf_counter()
    if params.stepping == "continuous":
        if len(controllers) != 1 or batch != 1:
            raise ConfigError("evaluate: the continuous-time diagram plays one episode at a time (batch 1); batches need stepping 'segment'")
        runner = RallyRunner(build_rally_diagram(params, controllers[0]), params)
        episodes = run_episodes(runner, shots, serve, seed, progress, skills)
    else:
        if len(controllers) not in (1, batch):
            raise ConfigError(f"evaluate: {len(controllers)} controllers for a batch of {batch}")
        policy = controllers if len(controllers) > 1 else controllers[0]
        runner = SegmentRallyRunner(build_segment_rally_diagram(params, policy, batch), params)
        seeds = seed * 1_000_003 + np.arange(len(shots))
        episodes = runner.run_many(shots, serve, seeds, skills, _batch_progress(len(shots), progress, start))
    return episodes


def _batch_progress(total: int, progress, start: float):
    """A ``run_many`` progress callback that reports every 10% of ``total`` episodes."""
    if progress is None:
        return None
    done = [0, 0]

    def report(ended: int) -> None:
        done[0] += ended
        if done[0] * 10 // total > done[1] or done[0] == total:
            done[1] = done[0] * 10 // total
            progress(f"evaluate: {done[0]}/{total} episodes, {time.perf_counter() - start:.0f} s")

    return report


def evaluate_controller(controller: str, *, sensors: str = "cameras", seed: int = 0, ball_params=None, data=None,
                        players: Sequence[str] = (), episodes: int | None = None, skill: str | None = None, skill_sampling=None,
                        action_noise: float = 0.0, stepping: str = "segment", batch: int = 32, progress: Callable[[str], None] = print,
                        make: Callable[[RallyParams], object] | None = None, repeats: int = 1) -> dict:
    """``ace-drake evaluate``: ``evaluate`` of the controller named ``controller``
    (``make_controller``; with ``action_noise`` > 0, Gaussian noise of that std in action units on
    every action, seeded) in the rally diagram of ``rally_params(ball_params, sensors, seed)``,
    on the human shots (shot_p2) of the match-data CSV ``data`` (of ``players`` only, if given),
    else ``episodes`` (default 200) shots of the synthetic distribution; at most ``episodes``
    episodes. The skill of every episode (``evaluation_skills``): ``skill`` "Y,WP,WS" for all, or
    "sampled": one per shot from ``skill_sampling``, or None: the diagram's default. Returns
    ``evaluate``'s figures with the settings, the provenance (command, date) and, with ``data``,
    its sha256. ``stepping``: "segment" (the batched diagram, ``batch`` episodes at a time) or
    "continuous" (the reference diagram, one at a time). ``make``, if given, builds the controller
    for a diagram's params instead of ``make_controller`` (e.g. a policy in memory, which
    ``controller`` then only names: ``training.export.final_evaluation``). ``repeats``: play every
    shot that many times, with seeds ``seed``, ``seed`` + 1, ... (each its own sensors', ball's
    and actions' noise; the shots and skills stay those drawn with ``seed``), the figures
    pooling them (``summarize``; ``wall_time_s`` the playing's, as for one) and each repeat's rate
    in ``return_rate_by_repeat``. Raises ConfigError for a bad option."""
    if episodes is not None and episodes < 1:
        raise ConfigError(f"evaluate: --episodes must be >= 1, got {episodes}")
    if repeats < 1:
        raise ConfigError(f"evaluate: --repeats must be >= 1, got {repeats}")
    players = tuple(players)
    if players and not data:
        raise ConfigError("evaluate: --players selects shots of --data; give a match-data CSV")
    if batch < 1:
        raise ConfigError(f"evaluate: --batch must be >= 1, got {batch}")
    if stepping == "continuous":
        batch = 1
    params = rally_params(ball_params, sensors, seed, stepping)
    if data:
        shots, serve = human_shots(data, players)
        shots, serve = shots[:episodes], serve[:episodes]
        of = f" of {', '.join(players)}" if players else ""
        source = f"the {len(shots)} human shots (shot_p2){of} of {data}"
    else:
        sample = make_distribution(ShotParams(seed=seed), params.physics).draw(np.random.default_rng(seed), episodes or 200)
        shots, serve = sample.states, sample.serve
        source = f"{len(shots)} shots from the built-in synthetic distribution"
    skills, skill_text = evaluation_skills(skill, len(shots), params, seed, skill_sampling)
    batch = max(1, min(batch, len(shots)))
    build = make or (lambda params: make_controller(controller, params))
    noise = f", Gaussian action noise {action_noise:g}" if action_noise else ""
    stepped = f", {stepping} diagram" + (f", {batch} at a time" if batch > 1 else "")
    seeds = f"seeds {seed}-{seed + repeats - 1} (each shot {repeats} times)" if repeats > 1 else f"seed {seed}"
    progress(f"evaluate: '{controller}'{noise} on {source}, {sensors} sensors, {seeds}, {skill_text}{stepped}")
    wall_time, episodes, by_repeat = 0.0, [], []
    for repeat_seed in range(seed, seed + repeats):
        if repeat_seed != seed:
            params = rally_params(ball_params, sensors, repeat_seed, stepping)
        controllers = _controllers(build, params, batch, action_noise, repeat_seed)
        start = time.perf_counter()
        played = play(controllers, params, shots, serve, repeat_seed, progress, skills, batch)
        wall_time += time.perf_counter() - start
        by_repeat.append(summarize(played)["return_rate"])
        episodes += played
    figures = {**summarize(episodes, len(shots) if repeats > 1 else None), "wall_time_s": wall_time, "stepping": stepping, "batch": batch}
    if repeats > 1:
        figures["return_rate_by_repeat"] = by_repeat
    return {"controller": controller, "action_noise": action_noise, "data": data, "players": list(players), "sensors": sensors,
            "seed": seed, "repeats": repeats, "skills": skill or "default", "ball_params": str(ball_params) if ball_params else None,
            **figures, **provenance(), **({"data_sha256": sha256(data)} if data else {})}


def _controllers(build: Callable[[RallyParams], object], params: RallyParams, batch: int, action_noise: float, seed: int):
    """What ``play`` takes for ``evaluate_controller``: the controller ``build(params)`` makes, or,
    for one with a memory (a reset()) or with action noise, ``batch`` of them (one per environment,
    the noise seeded by ``seed``)."""
    first = build(params)
    stateful = callable(getattr(first, "reset", None)) or action_noise > 0
    controllers = [first] + [build(params) for _ in range(batch - 1)] if stateful else [first]
    if action_noise:
        controllers = [NoisyActions(player, action_noise, seed=seed) for player in controllers]
    return controllers if len(controllers) > 1 else controllers[0]


def evaluation_skills(spec: str | None, count: int, params: RallyParams, seed: int, skill_sampling=None) -> tuple[np.ndarray | None, str]:
    """The skills of ``evaluate --skill``: None (the diagram's default), one fixed skill
    "Y,WP,WS" (y_desired in m, w_p in [0, 1], w_s in [-1, 1]) for every shot, or "sampled": one
    per shot from ``skill_sampling`` (the training distribution, ``training.env.SkillSampling``:
    its ``sample(rng, table_width)``) drawn with ``seed``. Returns (skills (count, 3) or None, a
    phrase for the log); raises ConfigError for anything else."""
    if spec is None:
        return None, "the default skill (y_desired 0 m, w_p 1, w_s 0)"
    if spec == "sampled":
        if skill_sampling is None:
            raise ValueError("evaluation_skills: 'sampled' needs the skill_sampling to draw from")
        rng = np.random.default_rng([seed, 0x5C111])
        skills = np.array([skill_sampling.sample(rng, params.physics.table.width) for _ in range(count)]).reshape(count, 3)
        return skills, "skills sampled as in training"
    try:
        skill = np.array([float(value) for value in spec.split(",")])
    except ValueError:
        skill = np.array([])
    if skill.shape != (3,) or not np.all(np.isfinite(skill)) or not (0.0 <= skill[1] <= 1.0 and -1.0 <= skill[2] <= 1.0):
        raise ConfigError(f"evaluate: --skill must be 'sampled' or Y,WP,WS (y_desired in m, w_p in [0, 1], w_s in [-1, 1]), got {spec!r}")
    return np.tile(skill, (count, 1)), f"skill y_desired {skill[0]:g} m, w_p {skill[1]:g}, w_s {skill[2]:g}"
