"""MatchTrack (evaluation.match_track) and the match's Meshcat HTML replay (analysis.match_replay),
the replay checked in a real headless Chromium: it loads without errors, plays, and its point
links seek the animation; the drawn ball and racket sit where the track puts them."""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest

from ace_drake.analysis.match_replay import ball_keyframes, with_point_panel, write_match_replay
from ace_drake.evaluation.match_track import MatchTrack, TrackPoint
from ace_drake.robot.model import RobotModel, load_scenario

CHROMIUM = Path("/usr/bin/chromium")  # Debian's package, installed by ./run.sh test
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]
BROWSER_TIMEOUT_MS = 45_000
FPS = 30.0
POINT_PERIOD = 6.0  # s: 4 s in play, then a 2 s pause without a ball; starts on the frame grid
LABELS = (
    "Point 1, game 1: 0-0, robot serves - robot won (double bounce)",
    "Point 2, game 1: 1-0, robot serves - human won (net) <&>",
    "Point 3, game 1: 1-1, human serves - robot won (missed return)",
)


def synthetic_track(rate: float = 100.0) -> MatchTrack:
    """Three points of POINT_PERIOD s sampled at ``rate`` Hz: the robot swings from the ready pose
    towards its upper joint limits and back, the ball flies a parabola along +x for 4 s and is out
    of play in each 2 s pause."""
    scenario = load_scenario()
    ready = np.asarray(scenario.ready_pose)
    swung = ready + 0.3 * (scenario.limits.as_arrays()["upper"] - ready)
    times = np.arange(round(len(LABELS) * POINT_PERIOD * rate)) / rate
    s = np.mod(times, POINT_PERIOD)
    q = ready + np.sin(np.pi * np.clip(s / 4.0, 0, 1))[:, None] * (swung - ready)
    ball = np.stack([-1.3 + 0.6 * s, 0.1 * s, 0.3 + 0.5 * s * (4.0 - s)], axis=1)
    ball[s >= 4.0] = np.nan
    points = tuple(TrackPoint(i * POINT_PERIOD, label) for i, label in enumerate(LABELS))
    return MatchTrack(times, ball, q, points)


@pytest.fixture(scope="module")
def replay(tmp_path_factory):
    """The synthetic track, its replay's path and the writer's progress lines."""
    track = synthetic_track()
    lines = []
    path = write_match_replay(track, tmp_path_factory.mktemp("replay") / "match.html", fps=FPS, progress=lines.append)
    return track, path, lines


# ---------------------------------------------------------------------------------- MatchTrack
def _valid(n: int = 4) -> dict:
    return dict(times=np.arange(n) * 0.5, ball=np.zeros((n, 3)), q=np.zeros((n, 8)), points=(TrackPoint(0.0, "Point 1"),))


@pytest.mark.parametrize(
    "change, field",
    [
        (dict(times=np.zeros((4, 1))), "MatchTrack.times"),
        (dict(times=np.array([0.0, 0.5, 0.5, 1.0])), "MatchTrack.times"),
        (dict(times=np.array([-0.1, 0.5, 1.0, 1.5])), "MatchTrack.times"),
        (dict(times=np.array([0.0, np.nan, 1.0, 1.5])), "MatchTrack.times"),
        (dict(times=["a", "b", "c", "d"]), "MatchTrack.times"),
        (dict(ball=np.zeros((4, 2))), "MatchTrack.ball"),
        (dict(ball=np.array([[0, 0, 0], [np.nan, 0, 0], [0, 0, 0], [0, 0, 0]], dtype=float)), "MatchTrack.ball"),
        (dict(ball=np.array([[0, 0, 0], [np.inf, 0, 0], [0, 0, 0], [0, 0, 0]], dtype=float)), "MatchTrack.ball"),
        (dict(q=np.zeros((4, 7))), "MatchTrack.q"),
        (dict(q=np.where(np.eye(4, 8) > 0, np.nan, 0.0)), "MatchTrack.q"),
        (dict(points=(TrackPoint(2.0, "late"),)), r"MatchTrack.points\[0\].start_time"),
        (dict(points=(TrackPoint(1.0, "b"), TrackPoint(0.5, "a"))), r"MatchTrack.points\[1\].start_time"),
        (dict(points=("Point 1",)), r"MatchTrack.points\[0\]"),
    ],
)
def test_match_track_rejects_bad_fields(change, field):
    with pytest.raises(ValueError, match=field):
        MatchTrack(**{**_valid(), **change})


@pytest.mark.parametrize("start_time, label", [(math.nan, "Point 1"), (0.0, " "), ("0", "Point 1")])
def test_track_point_rejects_bad_fields(start_time, label):
    with pytest.raises(ValueError, match="TrackPoint"):
        TrackPoint(start_time, label)


def test_match_track_keeps_read_only_copies_and_nan_rows():
    fields = _valid()
    fields["ball"][1] = np.nan
    track = MatchTrack(**fields)
    fields["q"][0, 0] = 5.0
    assert track.q[0, 0] == 0.0 and not track.q.flags.writeable
    assert np.isnan(track.ball[1]).all() and track.duration == 1.5


def test_resampled_interpolates_on_the_frame_grid_and_hides_around_nan_rows():
    times = np.array([0.1, 0.5, 1.0])
    ball = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [np.nan] * 3])
    q = np.outer([0.0, 4.0, 6.0], np.ones(8))
    frames = MatchTrack(times, ball, q, (TrackPoint(0.5, "Point 1"),)).resampled(4.0)
    np.testing.assert_allclose(frames.times, [0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(frames.q[:, 0], [1.5, 4.0, 5.0, 6.0])  # by hand: 4 * 0.15 / 0.4, ...
    np.testing.assert_allclose(frames.ball[:2], [[0.375, 0.75, 1.125], [1.0, 2.0, 3.0]])
    assert np.isnan(frames.ball[2:]).all()
    assert frames.points == (TrackPoint(0.5, "Point 1"),)
    with pytest.raises(ValueError, match="fps"):
        frames.resampled(0.0)


# ---------------------------------------------------------------------------------- the writer
def test_ball_keyframes_hold_a_hidden_ball_where_it_was_last_seen():
    ball = np.array([[np.nan] * 3, [1.0, 2.0, 3.0], [np.nan] * 3, [4.0, 5.0, 6.0]])
    shown, p_WB = ball_keyframes(ball)
    np.testing.assert_array_equal(shown, [False, True, False, True])
    np.testing.assert_array_equal(p_WB, [[1, 2, 3], [1, 2, 3], [1, 2, 3], [4, 5, 6]])


def test_replay_html_lists_the_points(replay):
    track, path, lines = replay
    text = path.read_text(encoding="utf-8")
    assert "new MeshCat.Viewer" in text and 'id="match-points"' in text
    for point in track.points:
        assert f'data-start="{point.start_time!r}"' in text
    assert LABELS[0] in text and "human won (net) &lt;&amp;&gt;" in text and LABELS[1] not in text
    assert lines[0].startswith("match replay: 3 points") and lines[-1].startswith(f"match replay: wrote {path}")


def test_with_point_panel_refuses_html_that_is_not_meshcats():
    with pytest.raises(ValueError, match="Meshcat"):
        with_point_panel("<html><body></body></html>", ())


# ---------------------------------------------------------------------------------- the browser
# Meshcat draws Drake's z-up world under a rotated three.js scene: read positions in the scene frame.
SEEK_AND_LOCATE = """([time, ...paths]) => {
    window.matchReplay.jumpTo(time);
    return paths.map(path => {
        const object = viewer.scene_tree.find(path).object;
        const p = viewer.scene.worldToLocal(object.getWorldPosition(new MeshCat.THREE.Vector3()));
        return [p.x, p.y, p.z, object.visible];
    });
}"""
BALL, RACKET = ["match", "ball"], ["drake", "visualizer", "ace_robot", "racket"]  # Meshcat paths
ANIMATION_TIME = "() => Math.max(...viewer.animator.actions.map(action => action.time))"


def _racket_position(q: np.ndarray, model: RobotModel) -> np.ndarray:
    """p_WRacket (3,), m: the racket body's origin in world at joint positions q."""
    model.plant.SetPositions(model.plant_context, q)
    return model.plant.GetBodyByName("racket", model.robot).EvalPoseInWorld(model.plant_context).translation()


def test_replay_plays_and_seeks_to_points_in_headless_chromium(replay):
    if not os.access(CHROMIUM, os.X_OK):
        pytest.skip(f"{CHROMIUM} not installed (./run.sh test installs Debian's chromium as root with apt-get)")
    from playwright.sync_api import sync_playwright

    track, path, _ = replay
    errors = []
    with sync_playwright() as playwright, tempfile.TemporaryDirectory() as profile:
        browser = playwright.chromium.launch_persistent_context(
            profile, executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_FLAGS, timeout=BROWSER_TIMEOUT_MS,
            viewport={"width": 640, "height": 400},  # WebGL renders in software here: a small page keeps it quick
        )
        try:
            page = browser.new_page()
            page.set_default_timeout(BROWSER_TIMEOUT_MS)
            page.on("console", lambda message: errors.append(message.text) if message.type == "error" else None)
            page.on("pageerror", lambda error: errors.append(f"pageerror: {error}"))
            page.goto(path.as_uri())
            page.wait_for_function("typeof viewer !== 'undefined' && viewer.animator.actions.length > 0")
            assert not errors, f"browser console errors on loading: {errors}"

            # The animation covers the match and plays on its own.
            assert page.evaluate("viewer.animator.duration") == pytest.approx(track.duration, abs=1.5 / FPS)
            before = page.evaluate(ANIMATION_TIME)
            page.wait_for_function(f"({ANIMATION_TIME})() > {before} + 0.2")

            # Freeze the clock, then each link seeks to its point's start exactly.
            page.evaluate("viewer.animator.mixer.timeScale = 0")
            for index in (1, 2, 0):
                point = track.points[index]
                page.get_by_role("link", name=point.label).click()
                assert page.evaluate(ANIMATION_TIME) == pytest.approx(point.start_time, abs=1e-9)
                assert page.locator("#match-points li.current").inner_text().startswith(point.label)

            # The ball and the racket are where the track puts them; the ball hides in a pause.
            model = RobotModel(load_scenario())
            for time in (7.0, 13.5, 16.0, 17.0):
                row = int(np.argmin(np.abs(track.times - time)))
                (*p_ball, visible), (*p_racket, _) = page.evaluate(SEEK_AND_LOCATE, [time, BALL, RACKET])
                in_play = bool(np.isfinite(track.ball[row]).all())
                assert visible == in_play, f"ball visible {visible} at {time} s"
                if in_play:
                    np.testing.assert_allclose(p_ball, track.ball[row], atol=1e-5)
                np.testing.assert_allclose(p_racket, _racket_position(track.q[row], model), atol=1e-5)
        finally:
            browser.close()
    assert not errors, f"browser console errors: {errors}"
