"""A self-contained Meshcat HTML replay of a whole match, with its points listed and navigable.

``write_match_replay`` draws a ``MatchTrack`` (evaluation.match_track): the court and the robot
from the scenario's model files (``diagrams.build_robot_view_diagram``) posed by the track's joint
positions, and the ball, hidden while the
track has no ball in play. Everything is one Meshcat animation over the match's time line, saved
with ``Meshcat.StaticHtml()``. A panel lists the points; clicking one seeks the animation to the
point's start time and plays from there (``window.matchReplay.jumpTo(seconds)`` does the same from
the browser's console).
"""

from __future__ import annotations

import html
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
from pydrake.geometry import Meshcat, Sphere
from pydrake.math import RigidTransform

from ace_drake.evaluation.match_track import MatchTrack, TrackPoint
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.diagrams import build_robot_view_diagram
from ace_drake.robot.model import load_scenario
from ace_drake.robot.params import RobotScenario
from ace_drake.systems.ball_visualizer import BALL_COLOR, set_court_view

REPLAY_FPS = 30.0  # animation frames per s of match: ~3 MB of HTML per minute of match, ~2.3 MB of viewer
BALL_PATH = "/match/ball"  # the ball's Meshcat path (absolute, beside Drake's /drake tree)
PROGRESS_EVERY = 0.1  # fraction of the frames between progress messages


def write_match_replay(
    track: MatchTrack,
    path: str | Path,
    scenario: RobotScenario | None = None,
    fps: float = REPLAY_FPS,
    progress: Callable[[str], None] | None = None,
) -> Path:
    """Writes the match ``track`` as a self-contained Meshcat HTML replay at ``path`` (parent
    folders created) and returns the path. The robot and court are those of ``scenario`` (default
    models/scenario.yaml); the animation has ``fps`` frames per second of match time (the track is
    resampled, ``MatchTrack.resampled``). ``progress`` receives a line every tenth of the frames."""
    if not isinstance(track, MatchTrack):
        raise ValueError(f"write_match_replay: track must be a MatchTrack, got {type(track).__name__}")
    scenario = scenario or load_scenario()
    frames = track.resampled(fps)
    report = progress or (lambda line: None)
    meshcat = Meshcat()
    set_court_view(meshcat)
    view = build_robot_view_diagram(scenario, meshcat)
    diagram, plant, visualizer = view.diagram, view.plant, view.visualizer
    context = diagram.CreateDefaultContext()
    plant_context = plant.GetMyMutableContextFromRoot(context)
    visualizer_context = visualizer.GetMyContextFromRoot(context)
    meshcat.SetObject(BALL_PATH, Sphere(BallPhysicsParams().aero.ball_radius), BALL_COLOR)

    count = frames.times.size
    shown, p_WB = ball_keyframes(frames.ball)
    report(f"match replay: {len(track.points)} points, {track.duration:.1f} s of match, {count} frames at {fps:g} fps")

    def draw(index: int, time: float | None) -> None:
        plant.SetPositions(plant_context, frames.q[index])
        if time is not None:
            context.SetTime(time)
        visualizer.ForcedPublish(visualizer_context)
        meshcat.SetTransform(BALL_PATH, RigidTransform(p_WB[index]), time)
        if time is None or index == 0 or shown[index] != shown[index - 1]:
            meshcat.SetProperty(BALL_PATH, "visible", bool(shown[index]), time)

    # The first frame also poses the live scene, which the page shows until the animation loads.
    draw(0, None)
    meshcat.StartRecording(frames_per_second=fps, set_visualizations_while_recording=False)
    # Meshcat keys a recorded time t at frame floor(t * fps): k / fps itself can land on frame k - 1
    # by rounding, so each frame is drawn a quarter frame after its time (keyed at exactly k / fps).
    key_times = (np.round(frames.times * fps) + 0.25) / fps
    step = max(1, math.ceil(PROGRESS_EVERY * count))
    for index in range(count):
        draw(index, float(key_times[index]))
        if (index + 1) % step == 0 and index + 1 < count:
            report(f"match replay: {index + 1}/{count} frames ({frames.times[index]:.0f} of {track.duration:.0f} s)")
    meshcat.StopRecording()
    meshcat.PublishRecording()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(with_point_panel(meshcat.StaticHtml(), track.points), encoding="utf-8")
    report(f"match replay: wrote {path} ({path.stat().st_size / 1e6:.1f} MB)")
    return path


def ball_keyframes(ball: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For ball centres (F, 3), m, with NaN rows where no ball is in play: whether the ball is
    shown (F,) and where it is drawn (F, 3), m. A hidden ball is held where it was last seen (at
    the first sighting before that), so it never drifts visibly towards the next point's start."""
    shown = np.all(np.isfinite(ball), axis=1)
    if not shown.any():
        return shown, np.zeros_like(ball)
    last_seen = np.maximum.accumulate(np.where(shown, np.arange(len(ball)), -1))
    last_seen[last_seen < 0] = int(np.argmax(shown))
    return shown, ball[last_seen]


POINT_PANEL = """
<style>
  #match-points {
    position: fixed; left: 8px; top: 8px; z-index: 10; max-width: 28em; max-height: calc(100vh - 16px);
    overflow-y: auto; padding: 6px 10px; background: rgba(255, 255, 255, 0.9); border-radius: 4px;
    font: 13px/1.35 sans-serif; color: #222;
  }
  #match-points h2 { font-size: 14px; margin: 2px 0 4px; }
  #match-points ol { margin: 0; padding-left: 2.2em; }
  #match-points li.current { font-weight: bold; }
  #match-points a { color: #124; text-decoration: none; }
  #match-points a:hover { text-decoration: underline; }
</style>
<div id="match-points">
  <h2>Points <span id="match-clock"></span></h2>
  <ol>
__ITEMS__
  </ol>
</div>
<script>
// Point navigation over Meshcat's animator (the page's global ``viewer``; its ``animator`` holds
// one THREE.AnimationAction per drawn object, all on the match's time line in seconds).
(function () {
  "use strict";
  var items = Array.prototype.slice.call(document.querySelectorAll("#match-points li[data-start]"));
  var starts = items.map(function (item) { return parseFloat(item.getAttribute("data-start")); });
  var clock = document.getElementById("match-clock");

  function animator() {
    return (typeof viewer !== "undefined" && viewer.animator && viewer.animator.actions.length > 0) ? viewer.animator : null;
  }
  function currentTime() {
    var a = animator();
    return a ? a.actions.reduce(function (latest, action) { return Math.max(latest, action.time); }, 0) : 0;
  }
  function highlight(time) {
    var current = -1;
    starts.forEach(function (start, i) { if (start <= time + 1e-6) { current = i; } });
    items.forEach(function (item, i) { item.classList.toggle("current", i === current); });
    clock.textContent = "(" + time.toFixed(1) + " s)";
  }
  function jumpTo(time) {
    var a = animator();
    if (!a) { return false; }
    // Actions that reached the end stay paused (clampWhenFinished): wake them before seeking.
    a.actions.forEach(function (action) { action.paused = false; action.enabled = true; });
    a.seek(time);
    a.display_progress(time);
    if (!a.playing) { a.play(); }
    highlight(time);
    return true;
  }
  items.forEach(function (item, i) {
    item.querySelector("a").addEventListener("click", function (event) {
      event.preventDefault();
      jumpTo(starts[i]);
    });
  });
  setInterval(function () { highlight(currentTime()); }, 250);
  window.matchReplay = { starts: starts, jumpTo: jumpTo, currentTime: currentTime };
})();
</script>
"""


def with_point_panel(static_html: str, points: tuple[TrackPoint, ...]) -> str:
    """``static_html`` (a Meshcat ``StaticHtml()``) with the points' panel and its script added
    before ``</body>``: one link per point, labelled, that seeks the animation to its start."""
    if static_html.count("</body>") != 1 or "new MeshCat.Viewer" not in static_html:
        raise ValueError("with_point_panel: expected Meshcat's static HTML (one </body>, a MeshCat.Viewer)")
    items = "\n".join(
        f'    <li data-start="{point.start_time!r}"><a href="#">{html.escape(point.label)}</a> '
        f"<small>{_clock(point.start_time)}</small></li>"
        for point in points
    )
    if not points:
        items = "    <li>(no points)</li>"
    panel = POINT_PANEL.replace("__ITEMS__", items)
    head, tail = static_html.split("</body>")
    return f"{head}{panel}</body>{tail}"


def _clock(seconds: float) -> str:
    """m:ss of a time in s."""
    minutes, rest = divmod(int(seconds), 60)
    return f"{minutes}:{rest:02d}"

