"""Tutorial 01: how the ball flies, how it bounces, and how well the model replays a real rally.

Read this file top to bottom like a notebook. It shows

  1. flight (paper eq. (1)): the same launch with topspin, no spin and backspin, and why spin
     decides where the ball lands;
  2. the table bounce (paper eqs (2)-(6)): the velocity and spin just before and after the topspin
     ball's bounce, and whether the contact slid or rolled;
  3. a recorded rally from the robot's matches against elite players, replayed through the same ball
     model: how far each simulated bounce lands from the recorded one;
  4. the racket contact (paper eqs (7)-(8)) against contacts the real robot measured: the printed
     model, the model fitted on some games and judged on others (``ace-drake physics-fit-racket``
     does this with the residual network too);
  5. a Meshcat replay of parts 1 and 3 in 3D, saved as self-contained HTML files.

Everything runs through the project's BallPlant (a Drake LeafSystem) in one Diagram and Simulator
per part; the numbers are SI units throughout (m, s, rad). Run it from the repository root:

    .venv/bin/python tutorials/01_ball_flight.py                # all parts
    .venv/bin/python tutorials/01_ball_flight.py --no-html      # skip the Meshcat files
    .venv/bin/python tutorials/01_ball_flight.py --data PATH --out DIR

It writes ball_flight.png (parts 1-3), racket_contacts.png (part 4) and, unless --no-html,
spin_comparison.html and rally_replay.html into --out (default out/tutorials/01). Part 3 needs the
recorded match data (default ../shared/data/ace_match_events_elite.csv beside the repository), part
4 the measured racket contacts (../shared/data/sony_racket_contacts.csv, --contacts); without them
those parts are skipped. It takes a few seconds.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Patch
from pydrake.geometry import Meshcat

from ace_drake.analysis.ball_demo import run_shots, spin_comparison_shots, summarize_shots
from ace_drake.analysis.replay import longest_rallies, replay_rally
from ace_drake.match_data import load_match_events
from ace_drake.physics.contact import racket_restitution, table_alpha, table_restitution
from ace_drake.physics.flight import flight_acceleration
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind
from ace_drake.physics.racket_contacts import contact_errors, fit_racket_model, load_racket_contacts, predict_post_contact, split_by_game

matplotlib.use("Agg")  # write files only, never open a window

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO_ROOT.parent / "shared/data/ace_match_events_elite.csv"
DEFAULT_CONTACTS = REPO_ROOT.parent / "shared/data/sony_racket_contacts.csv"
DEFAULT_OUT = REPO_ROOT / "out/tutorials/01"
REPLAY_PLAYER = "Elite B"  # part 3 replays this opponent's longest rally
SPIN_COLORS = {"topspin": "tab:red", "no spin": "tab:gray", "backspin": "tab:blue"}


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="recorded match events CSV (part 3)")
    parser.add_argument("--contacts", type=Path, default=DEFAULT_CONTACTS, help="measured racket contacts CSV (part 4)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="directory for the PNG and HTML files")
    parser.add_argument("--no-html", action="store_true", help="skip the Meshcat HTML replays (part 5)")
    return parser.parse_args()


def save_html(meshcat, path: Path) -> None:
    """Writes the current Meshcat scene and recording as one self-contained HTML file."""
    path.write_text(meshcat.StaticHtml())
    print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB; open it in any browser)")


def draw_table_side_view(ax, params: BallPhysicsParams) -> None:
    """The playing surface (z = 0), the net and the floor in the x-z plane."""
    half_length = 0.5 * params.table.length
    ax.plot([-half_length, half_length], [0.0, 0.0], color="tab:green", linewidth=4, label="table surface")
    ax.plot([0.0, 0.0], [0.0, params.net.height], color="black", linewidth=2, label="net")
    ax.axhline(-params.table.surface_height, color="saddlebrown", linewidth=1, label="floor")


def draw_table_top_view(ax, params: BallPhysicsParams) -> None:
    """The table's outline, centre line and net in the x-y plane."""
    half_length, half_width = 0.5 * params.table.length, 0.5 * params.table.width
    corners_x = [-half_length, half_length, half_length, -half_length, -half_length]
    corners_y = [-half_width, -half_width, half_width, half_width, -half_width]
    ax.fill(corners_x, corners_y, color="tab:green", alpha=0.15)
    ax.plot(corners_x, corners_y, color="tab:green", linewidth=1.5)
    ax.plot([-half_length, half_length], [0.0, 0.0], color="tab:green", linewidth=0.5)
    net_half_span = half_width + params.net.overhang
    ax.plot([0.0, 0.0], [-net_half_span, net_half_span], color="black", linewidth=2)


def main() -> None:
    args = parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    params = BallPhysicsParams()  # the paper's ball model, with the authors' published constants
    # One Meshcat viewer (a local web server); parts 1 and 3 record into it and save HTML files.
    meshcat = None if args.no_html else Meshcat()

    figure = plt.figure(figsize=(12, 9), layout="constrained")
    grid = figure.add_gridspec(2, 2, height_ratios=[1.0, 1.15], width_ratios=[1.3, 1.0])
    side_view = figure.add_subplot(grid[0, :])

    # ------------------------------------------------------------------------------------------
    # 1. Flight with drag, Magnus and gravity: paper eq. (1)
    # ------------------------------------------------------------------------------------------
    # In flight the ball feels three forces. Divided by its mass (paper eq. (1)):
    #     a = -(3 / (8 r)) c_d (rho_air / rho_ball) |v| v        drag, against the velocity
    #         - c_M (rho_air / rho_ball) (v x w)                 Magnus, across velocity and spin
    #         + (1 - rho_air / rho_ball) g                       gravity less buoyancy
    # with c_M = min(0.1 |v| / (r |w|) - 0.001, 1). Spin w stays constant in flight. A light ball
    # (2.7 g) makes drag and Magnus large next to gravity: the numbers below show how large.
    print("== 1. Flight: the same launch with topspin, no spin and backspin ==")
    shots = spin_comparison_shots()  # launched from the robot's side towards +x; spin about y
    topspin = shots["topspin"]
    v_W, w_W = topspin[3:6], topspin[6:9]
    zero = np.zeros(3)
    # Each force alone, read off the full model: gravity at rest, drag without spin, Magnus as the
    # difference spin makes.
    gravity = flight_acceleration(zero, zero, params.aero)
    drag = flight_acceleration(v_W, zero, params.aero) - gravity
    magnus = flight_acceleration(v_W, w_W, params.aero) - drag - gravity
    print(f"launch speed {np.linalg.norm(v_W):.2f} m/s, topspin {w_W[1]:.0f} rad/s about +y")
    for name, a in [("gravity", gravity), ("drag", drag), ("Magnus", magnus)]:
        print(f"  {name:<8} {np.linalg.norm(a):5.2f} m/s^2  direction {np.round(a / np.linalg.norm(a), 2)}")
    # Topspin (w along +y for a ball moving +x) makes v x w point up, so the Magnus term
    # -c_M (v x w) pushes the ball down: it dips and lands short. Backspin lifts it and it floats long.

    results = run_shots(shots, params, duration=1.2, meshcat=meshcat)  # one Diagram, one Simulator
    print(f"{'shot':<10}{'net clearance':>14}{'bounce (x, y) m':>20}{'at t':>9}{'speed after':>13}{'spin after':>22}")
    for row in summarize_shots(results):
        x, y = row["bounce_position_m"]
        spin = np.round(row["spin_after_bounce_radps"]).astype(int)
        print(
            f"{row['shot']:<10}{100 * row['net_clearance_m']:>11.1f} cm{f'({x:+.2f}, {y:+.2f})':>20}"
            f"{row['bounce_time_s']:>7.3f} s{row['speed_after_bounce_mps']:>9.2f} m/s{str(spin):>18} rad/s"
        )
    if meshcat is not None:
        save_html(meshcat, args.out / "spin_comparison.html")
        written.append(args.out / "spin_comparison.html")

    draw_table_side_view(side_view, params)
    for result in results:
        side_view.plot(result.states[:, 0], result.states[:, 2], color=SPIN_COLORS[result.name], label=result.name)
        bounce = result.first(ContactKind.TABLE)
        side_view.plot(bounce.state_pre[0], bounce.state_pre[2], "o", color=SPIN_COLORS[result.name])
    side_view.set(
        title="1. One launch, three spins (side view; dots: first bounce)",
        xlabel="x, along the table (m)",
        ylabel="z, ball centre height (m)",
        xlim=(-1.8, 3.0),
        ylim=(-0.8, 0.6),
        aspect="equal",
    )
    side_view.legend(loc="lower left", ncols=2, fontsize=9)

    # ------------------------------------------------------------------------------------------
    # 2. The table bounce: paper eqs (2)-(6)
    # ------------------------------------------------------------------------------------------
    # A bounce is instantaneous: position stays, velocity and spin jump by a linear map
    #     v+ = C_vv v- + C_vw w-   (eq. (2)),     w+ = C_wv v- + C_ww w-   (eq. (3)).
    # Normal velocity reverses with restitution eps = 0.98 - 0.02 |v_z-| (eq. (6)). Along the table,
    # friction acts on the slip of the contact point, v_T = [v_x - r w_y, v_y + r w_x]: if the
    # friction impulse mu (1 + eps) |v_z| is too small to stop that slip the ball keeps sliding
    # and alpha = mu (1 + eps) |v_z| / |v_T| (eqs (4)-(5)); otherwise it grips and leaves rolling,
    # alpha = 2/5, and then v_x+ = r w_y+ exactly. Topspin already turns the ball's bottom
    # backwards, so its slip is small: it grips and kicks on fast (here it even gains forward speed).
    # Backspin turns the bottom forwards, adding to the slip: friction eats its forward speed.
    print("\n== 2. The bounce: velocity and spin before and after (eqs (2)-(6)) ==")
    radius = params.aero.ball_radius
    for result in results:
        bounce = result.first(ContactKind.TABLE)
        v_pre, w_pre = bounce.state_pre[3:6], bounce.state_pre[6:9]
        v_post, w_post = bounce.state_post[3:6], bounce.state_post[6:9]
        alpha, sliding = table_alpha(v_pre, w_pre, params.table, radius)
        slip = np.hypot(v_pre[0] - radius * w_pre[1], v_pre[1] + radius * w_pre[0])
        if result.name == "topspin":
            print(f"topspin ball at t = {bounce.time:.3f} s, (x, y) = ({bounce.state_pre[0]:+.2f}, {bounce.state_pre[1]:+.2f}) m")
            print(f"  v before {np.round(v_pre, 2)} m/s   after {np.round(v_post, 2)} m/s")
            print(f"  w before {np.round(w_pre, 1)} rad/s   after {np.round(w_post, 1)} rad/s")
            print(f"  restitution eps = {float(table_restitution(v_pre[2], params.table)):.3f} (v_z {v_pre[2]:.2f} -> {v_post[2]:.2f} m/s)")
        regime = "slides" if sliding else "rolls"
        print(
            f"  {result.name:<9} slip |v_T| {slip:4.2f} m/s -> alpha {float(alpha):.3f}, {regime}; "
            f"forward speed {v_pre[0]:.2f} -> {v_post[0]:.2f} m/s, w_y {w_pre[1]:+.0f} -> {w_post[1]:+.0f} rad/s"
        )

    # ------------------------------------------------------------------------------------------
    # 3. Replaying a recorded rally
    # ------------------------------------------------------------------------------------------
    # The data hold the ball's state just after every shot, bounce and net event that the real
    # robot's cameras saw. The rackets are not modelled here, so replay_rally sets the ball to the
    # recorded post-shot state at each shot and lets the model fly and bounce it in between. Each
    # recorded bounce is compared with the simulated table contact nearest in time. Errors come from
    # both the model (paper constants, no fitting) and the recorded states (estimated from
    # cameras); a ball that clips the net in the model but not in reality shows as a large miss.
    print("\n== 3. Replaying a recorded rally ==")
    top_view = figure.add_subplot(grid[1, 0])
    distance_plot = figure.add_subplot(grid[1, 1])
    replay = None
    if not args.data.is_file():
        print(f"match data not found at {args.data}: skipping part 3 (pass --data PATH to the CSV)")
        for ax in (top_view, distance_plot):
            ax.text(0.5, 0.5, "no match data: part 3 skipped", ha="center", va="center", transform=ax.transAxes)
            ax.set_axis_off()
    else:
        events = load_match_events(args.data)
        key = longest_rallies(events, 1, player=REPLAY_PLAYER)[0]
        if meshcat is not None:
            meshcat.Delete()  # a fresh scene and recording for the rally
            meshcat.DeleteRecording()
        replay = replay_rally(events, params, meshcat, rally=key.rally, player=key.player)
        shots_in_rally = sum(e.kind == "shot" for e in replay.recorded)
        print(f"{key.player} {key.rally}: {shots_in_rally} shots, {replay.times[-1]:.1f} s simulated")
        print(f"{'bounce':>6}{'recorded t':>12}{'side':>6}{'distance':>11}{'time error':>12}")
        for index, comparison in enumerate(replay.bounces):
            side = "robot" if comparison.recorded.side == "p1" else "human"
            print(
                f"{index:>6}{comparison.recorded.time:>10.3f} s{side:>6}"
                f"{100 * comparison.distance:>8.1f} cm{1000 * comparison.time_error:>+9.0f} ms"
            )
        distances = replay.bounce_distances
        print(f"median distance {100 * np.median(distances):.1f} cm, worst {100 * np.max(distances):.1f} cm")
        if meshcat is not None:
            save_html(meshcat, args.out / "rally_replay.html")
            written.append(args.out / "rally_replay.html")

        # Top view: the simulated ball between resets, its table contacts, and the recorded bounces.
        draw_table_top_view(top_view, params)
        reset_times = [replay.recorded[0].time] + [e.time for e in replay.recorded[1:] if e.kind == "shot"]
        breaks = np.searchsorted(replay.times, reset_times[1:])
        for segment in np.split(replay.states, breaks):
            top_view.plot(segment[:, 0], segment[:, 1], color="tab:orange", linewidth=0.8, alpha=0.7)
        top_view.plot([], [], color="tab:orange", label="simulated ball")
        table_contacts = np.array([e.state_pre[:2] for e in replay.contact_events if e.kind == ContactKind.TABLE])
        top_view.plot(*table_contacts.T, "x", color="tab:red", label="simulated bounce")
        recorded_bounces = np.array([c.recorded.state[:2] for c in replay.bounces])
        top_view.plot(*recorded_bounces.T, "o", mfc="none", color="tab:green", label="recorded bounce")
        matched = [c for c in replay.bounces if c.simulated is not None]
        for index, comparison in enumerate(matched):
            pair = np.stack([comparison.recorded.state[:2], comparison.simulated.state_pre[:2]])
            top_view.plot(*pair.T, color="black", linewidth=0.8, label="compared pair" if index == 0 else None)
        shot_positions = np.array([e.state[:2] for e in replay.recorded if e.kind == "shot"])
        top_view.plot(*shot_positions.T, ".", color="tab:purple", label="recorded shot (reset)")
        top_view.set(
            title=f"3. Replay of {key.player} {key.rally} (top view)",
            xlabel="x, along the table (m)",
            ylabel="y, across the table (m)",
            xlim=(-2.6, 2.6),
            ylim=(-1.4, 1.4),
            aspect="equal",
        )
        top_view.legend(loc="lower center", ncols=3, fontsize=8)

        bounce_times = [c.recorded.time for c in replay.bounces]
        colors = ["tab:blue" if c.recorded.side == "p1" else "tab:olive" for c in replay.bounces]
        distance_plot.bar(bounce_times, 100 * distances, width=0.15, color=colors)
        distance_plot.axhline(100 * np.median(distances), color="black", linestyle="--", label="median")
        distance_plot.set(
            title="3. Simulated vs recorded bounce position",
            xlabel="time in rally (s)",
            ylabel="distance between bounces (cm)",
        )
        side_patches = [Patch(color="tab:blue", label="on the robot's half"), Patch(color="tab:olive", label="on the human's half")]
        distance_plot.legend(handles=[*side_patches, *distance_plot.get_legend_handles_labels()[0]], fontsize=9)

    png = args.out / "ball_flight.png"
    figure.savefig(png, dpi=110)
    written.insert(0, png)

    # ------------------------------------------------------------------------------------------
    # 4. The racket contact against measured contacts: paper eqs (7)-(8)
    # ------------------------------------------------------------------------------------------
    # At the racket the ball's velocity relative to the blade's surface point, in the contact frame C
    # (z along the blade normal), is mapped linearly: the normal part reverses with restitution
    # eps(|v_n|), the tangential part keeps (1 - k) of itself plus k r times the spin's cross term,
    # and the spin changes by the slip (eq. (8)). The real robot measured 572 such contacts (ball
    # before and after, racket velocity and orientation). Contacts of one game are correlated, so
    # the fit holds out whole games and is judged on them.
    print("\n== 4. The racket contact against measured contacts (eqs (7)-(8)) ==")
    if not args.contacts.is_file():
        print(f"racket contacts not found at {args.contacts}: skipping part 4 (pass --contacts PATH to the CSV)")
    else:
        contacts = load_racket_contacts(args.contacts)
        held, games = split_by_game(contacts, holdout_fraction=0.2, seed=0)
        fit = fit_racket_model(contacts.subset(~held), "exponential", params)
        test = contacts.subset(held)
        print(f"{len(contacts)} contacts in {len(set(contacts.games))} games; fitted on {int((~held).sum())}, "
              f"judged on the {len(test)} of {len(games)} held-out games")
        print(f"fitted k {fit.parameters['tangential_k']:.3f}, eps = {fit.parameters['restitution_gamma1']:.3f} "
              f"exp({fit.parameters['restitution_gamma2']:.4f} |v_n|) (printed defaults: k {params.racket.tangential_k:.3f}, "
              f"eps = {params.racket.restitution_gamma1:.3f} exp({params.racket.restitution_gamma2:.4f} |v_n|))")
        racket_figure, axes = plt.subplots(1, 2, figsize=(11, 4.5), constrained_layout=True)
        for name, racket in (("printed", params.racket), ("fitted", fit.racket)):
            v_post, w_post = predict_post_contact(test, racket, params.aero.ball_radius)
            velocity_error, spin_error = contact_errors(test, v_post, w_post)
            print(f"  {name:<8} held-out error: velocity median {np.median(velocity_error):.2f} m/s "
                  f"(p90 {np.percentile(velocity_error, 90):.2f}), spin median {np.median(spin_error):.0f} rad/s")
            axes[0].plot(np.linalg.norm(test.v_post, axis=1), np.linalg.norm(v_post, axis=1), ".", alpha=0.6, label=f"{name} model")
        speeds = np.linspace(0.0, 25.0, 2)
        axes[0].plot(speeds, speeds, color="black", linewidth=0.8)
        axes[0].set(title="4. Outgoing ball speed, held-out contacts", xlabel="measured (m/s)", ylabel="model (m/s)")
        axes[0].legend()
        normal_speed = np.linspace(0.5, 20.0, 100)
        for name, racket in (("printed", params.racket), ("fitted", fit.racket)):
            axes[1].plot(normal_speed, racket_restitution(normal_speed, racket), label=f"{name} eps(|v_n|)")
        axes[1].set(title="4. Racket restitution", xlabel="normal speed into the blade |v_n| (m/s)", ylabel="eps")
        axes[1].legend()
        racket_png = args.out / "racket_contacts.png"
        racket_figure.savefig(racket_png, dpi=110)
        written.insert(1, racket_png)

    # ------------------------------------------------------------------------------------------
    # 5. Looking at it in 3D
    # ------------------------------------------------------------------------------------------
    # Parts 1 and 3 passed a Meshcat to run_shots and replay_rally, which recorded the ball (orange,
    # with a trail) while simulating; StaticHtml() then bundled scene and recording into one file
    # that plays in any browser. In the rally replay, green dots are the recorded bounces.
    print("\n== 5. Files ==")
    if meshcat is None:
        print("(--no-html: Meshcat replays skipped)")
    for path in written:
        print(f"  {path}")


if __name__ == "__main__":
    main()
