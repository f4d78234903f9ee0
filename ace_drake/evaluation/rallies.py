"""The main job's rallies: a controller against the launcher opponent on one replayable time line.

Each rally is one episode (paper, *Rally*): the opponent's shot drawn from the incoming-shot
distribution, the robot's response through the full rally diagram. The episodes run back to back
on one time line (each starts on a 32 ms boundary after the previous one's end, plus a pause) so
that a Meshcat recording of the Simulator is one continuous replay of all of them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
from pydrake.geometry import Meshcat

from ace_drake.contracts import Outcome
from ace_drake.control.params import RallyParams
from ace_drake.diagrams import build_rally_diagram, build_segment_rally_diagram
from ace_drake.evaluation.controllers import diagram_params_for, hit_state_controller, make_controller, rally_params
from ace_drake.evaluation.runner import Episode, RallyRunner, SegmentRallyRunner
from ace_drake.play.opponent import Launcher
from ace_drake.play.params import ShotParams
from ace_drake.play.shots import make_distribution

PAUSE = 0.5  # s between two rallies in the replay


def play_rallies(
    controller,
    params: RallyParams,
    shots: ShotParams,
    count: int,
    seed: int = 0,
    meshcat: Meshcat | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[tuple[Episode, bool]]:
    """Plays ``count`` rallies of ``controller`` against the launcher (shots drawn from
    ``shots`` with ``seed``) and returns each episode with whether its shot was a serve. With
    ``meshcat``, the robot, court and ball are drawn and recorded (publish the recording and
    take ``meshcat.StaticHtml()`` for a self-contained replay). The diagram computes the
    observation's hit prediction only if the controller reads it
    (``evaluation.controllers.diagram_params_for``)."""

    controller = hit_state_controller(controller, params)
    params = diagram_params_for(controller, params)

    if count < 1:
        raise ValueError(f"play_rallies: count must be >= 1, got {count}")
    rng = np.random.default_rng(seed)
    launcher = Launcher(make_distribution(shots, params.physics))
    runner = RallyRunner(build_rally_diagram(params, controller, meshcat), params)
    period = params.control.segment_samples * 1e-3
    if meshcat is not None:
        meshcat.StartRecording(frames_per_second=60.0, set_visualizations_while_recording=False)
    played, start = [], 0.0
    for index in range(count):
        shot, kind = launcher.shot(rng)
        episode = runner.run(shot, seed=seed * 1_000_003 + index, serve=kind == "serve", start_time=start)
        played.append((episode, kind == "serve"))
        start += math.ceil((episode.duration + PAUSE) / period) * period
        if progress is not None:
            progress(f"rally {index + 1}/{count}: {episode.result.outcome.value} {episode.result.reason}".rstrip())
    if meshcat is not None:
        meshcat.StopRecording()
        meshcat.PublishRecording()
    return played


def rally_rows(played: list[tuple[Episode, bool]]) -> list[dict]:
    """One summary row per rally: the shot (kind, speed m/s, spin rad/s), the outcome and its
    reason, the return's speed after the hit (m/s) and where it landed (m), the segments."""
    rows = []
    for episode, serve in played:
        result = episode.result
        row = {
            "shot": "serve" if serve else "return",
            "incoming_speed_m_s": float(np.linalg.norm(episode.shot[3:6])),
            "incoming_spin_rad_s": float(np.linalg.norm(episode.shot[6:9])),
            "outcome": result.outcome.value,
            "reason": result.reason,
            "outgoing_speed_m_s": None if result.hit is None else float(np.linalg.norm(result.hit.state_post[3:6])),
            "landing_m": None if result.outcome is not Outcome.RETURNED else [float(v) for v in result.landing.state_pre[:2]],
            "segments_accepted": episode.segments[0],
            "segments_refused": episode.segments[1],
        }
        rows.append(row)
    return rows


def play_rally_batch(controllers, params: RallyParams, shots: ShotParams, count: int, seed: int = 0, batch: int = 8,
                     progress: Callable[[str], None] | None = None) -> list[tuple[Episode, bool]]:
    """``play_rallies`` on the segment-stepped diagram (``params.stepping`` "segment"), ``batch``
    rallies at a time (``SegmentRallyRunner``), with the same shots and seeds; ``controllers``: one
    controller, or ``batch`` of them when it remembers its episode (a ``reset()``). No replay: the
    Meshcat drawing is the continuous-time diagram's."""
    controllers = list(controllers) if isinstance(controllers, (list, tuple)) else [controllers]
    controllers = [hit_state_controller(c, params) for c in controllers]
    params = diagram_params_for(controllers[0], params)
    if count < 1 or batch < 1:
        raise ValueError(f"play_rally_batch: count and batch must be >= 1, got {count}, {batch}")
    rng = np.random.default_rng(seed)
    launcher = Launcher(make_distribution(shots, params.physics))
    drawn = [launcher.shot(rng) for _ in range(count)]
    states = np.array([shot for shot, _ in drawn])
    serve = np.array([kind == "serve" for _, kind in drawn])
    policy = controllers if len(controllers) > 1 else controllers[0]
    runner = SegmentRallyRunner(build_segment_rally_diagram(params, policy, batch), params)
    done = [0]

    def report(ended: int) -> None:
        done[0] += ended
        if progress is not None:
            progress(f"rally: {done[0]}/{count} played")

    episodes = runner.run_many(states, serve, seed * 1_000_003 + np.arange(count), progress=report)
    return list(zip(episodes, serve.tolist()))


def run_rallies(controller: str, rallies: int = 5, sensors: str = "cameras", seed: int = 0, ball_params=None, html=None,
                batch: int = 8, progress: Callable[[str], None] = print) -> dict:
    """``ace-drake rally``: ``rallies`` rallies of the controller named ``controller``
    (``make_controller``) against the launcher, with the rally diagram of ``rally_params``. With
    ``html`` (a path) on the continuous-time diagram, one after another, drawn into a
    self-contained Meshcat replay written there; without, on the segment-stepped diagram,
    ``batch`` at a time. Returns ``returned`` (of the playable shots), ``played`` (the playable
    shots) and ``rallies`` (``rally_rows``)."""
    stepping = "continuous" if html else "segment"
    params = rally_params(ball_params, sensors, seed, stepping)
    progress(f"rally: {rallies} rallies of '{controller}' against the launcher ({sensors} sensors, seed {seed}, the {stepping} diagram)")
    if html:
        meshcat = Meshcat()
        played = play_rallies(make_controller(controller, params), params, ShotParams(seed=seed), rallies, seed, meshcat, progress=progress)
    else:
        batch = max(1, min(batch, rallies))
        first = make_controller(controller, params)
        players = [first] + [make_controller(controller, params) for _ in range(batch - 1)] if callable(getattr(first, "reset", None)) else first
        played = play_rally_batch(players, params, ShotParams(seed=seed), rallies, seed, batch, progress)
    rows = rally_rows(played)
    if html:
        path = Path(html)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(meshcat.StaticHtml())
        progress(f"wrote Meshcat replay {path} ({path.stat().st_size / 1e6:.1f} MB); open it in any browser")
    return {"returned": sum(row["outcome"] == "returned" for row in rows),
            "played": sum(row["outcome"] != "invalid" for row in rows), "rallies": rows}
