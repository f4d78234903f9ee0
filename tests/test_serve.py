"""control.serve: the toss, the gene mapping, the simulated serve judged by the umpire, and the
fitness."""

import dataclasses
import math

import numpy as np
import pytest

from ace_drake.control import serve
from ace_drake.control.serve import (
    GENE_RANGES,
    SERVE_GENES,
    SERVE_KINDS,
    STRIKE_HEIGHT_MIN,
    ServeWeights,
    Strike,
    TossState,
    serve_fitness,
    simulate_serve,
    simulate_serves,
    strike_from_genes,
)
from ace_drake.physics.contact import ball_in_racket_frame, blade_standoff, racket_gap
from ace_drake.physics.params import BallPhysicsParams
from ace_drake.physics.propagate import ContactKind
from ace_drake.physics.racket_inverse import contact_frame
from ace_drake.play.umpire import MIN_TOSS_RISE

PHYSICS = BallPhysicsParams()
TOSS = TossState()
LONG_TOPSPIN = SERVE_KINDS["long_topspin"]


def hand_strike(time, normal, racket_velocity) -> Strike:
    """A strike at ``time`` s meeting the tossed ball at the blade's centre, blade normal
    ``normal`` (not normalised), racket velocity (m/s), roll 0."""
    n = np.asarray(normal, dtype=float) / np.linalg.norm(normal)
    p_WB = serve.toss_ball(TOSS, PHYSICS, time)[:3]
    p_WR = p_WB - blade_standoff(PHYSICS.aero.ball_radius, PHYSICS.racket) * n
    return Strike(time, p_WR, contact_frame(n), np.asarray(racket_velocity, dtype=float))


# --- the toss -------------------------------------------------------------------------------


def test_the_default_toss_rises_enough_behind_the_end_line():
    toss = serve.umpire_toss(TOSS, PHYSICS)
    assert MIN_TOSS_RISE < toss.apex_height < 2.0**2 / (2 * 9.81)  # drag takes a little off 0.204 m
    assert toss.tilt == 0.0
    assert TOSS.position[0] < -0.5 * PHYSICS.table.length


def test_toss_ball_is_the_free_flight_and_the_same_in_any_batch():
    times = np.array([0.0, 0.1234, 0.3, 0.4])
    states = serve.toss_ball(TOSS, PHYSICS, times)
    np.testing.assert_array_equal(states[0], TOSS.state)
    for t, state in zip(times, states):
        np.testing.assert_array_equal(serve.toss_ball(TOSS, PHYSICS, t), state)
    # Against the drag-free flight: within drag's few millimetres.
    z = TOSS.position[2] + 2.0 * times - 0.5 * 9.81 * times**2
    np.testing.assert_allclose(states[:, 2], z, atol=5e-3)
    np.testing.assert_allclose(states[:, :2], np.broadcast_to(TOSS.position[:2], (4, 2)))


def test_a_toss_must_rise():
    with pytest.raises(ValueError, match="velocity"):
        TossState(velocity=np.array([0.0, 0.0, -1.0]))


# --- the gene mapping -----------------------------------------------------------------------


@pytest.mark.parametrize("gene", [0.0, 1.0])
def test_the_gene_mapping_reaches_each_end_of_its_documented_ranges(gene):
    strike = strike_from_genes(np.full(SERVE_GENES, gene), TOSS, PHYSICS)
    end = int(gene)
    ranges = {name: bounds[end] for name, bounds in GENE_RANGES.items()}
    t_first, t_last = serve.strike_window(TOSS, PHYSICS)
    assert strike.time == pytest.approx((t_first, t_last)[end], abs=1e-15)
    ball = serve.toss_ball(TOSS, PHYSICS, strike.time)
    assert ball[5] < 0.0  # falling (Law 2.6.3)
    if end == 1:
        assert ball[2] == pytest.approx(STRIKE_HEIGHT_MIN, abs=1e-5)
    n = strike.normal
    elevation, azimuth = ranges["elevation"], ranges["azimuth"]
    np.testing.assert_allclose(n, [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)], atol=1e-12)
    up = contact_frame(n)[:, 0]
    side = np.cross(up, n)
    assert side[2] == pytest.approx(0.0, abs=1e-12)  # the side tangent is horizontal
    assert strike.v_WR @ n == pytest.approx(ranges["normal_speed"])
    assert strike.v_WR @ up == pytest.approx(ranges["brush_up"])
    assert strike.v_WR @ side == pytest.approx(ranges["brush_side"])
    assert np.linalg.norm(strike.v_WR) <= 12.0
    p_RB = ball_in_racket_frame(ball[:3], strike.p_WR, strike.R_WR)
    np.testing.assert_allclose(p_RB, [ranges["contact_x"], ranges["contact_y"], blade_standoff(PHYSICS.aero.ball_radius, PHYSICS.racket)], atol=1e-12)
    assert np.hypot(*p_RB[:2]) < PHYSICS.racket.blade_radius
    assert racket_gap(ball[:3], strike.p_WR, strike.R_WR, PHYSICS.racket, PHYSICS.aero.ball_radius) == pytest.approx(0.0, abs=1e-12)
    roll = math.atan2(strike.R_WR[:, 0] @ contact_frame(n)[:, 1], strike.R_WR[:, 0] @ up)
    assert abs(roll) == pytest.approx(math.pi)  # -pi and pi are the same roll
    np.testing.assert_allclose(strike.R_WR.T @ strike.R_WR, np.eye(3), atol=1e-12)
    assert np.linalg.det(strike.R_WR) == pytest.approx(1.0)


def test_the_gene_mapping_is_batched_and_rejects_genes_outside_the_unit_box():
    genes = np.random.default_rng(0).uniform(0.0, 1.0, (5, SERVE_GENES))
    batch = strike_from_genes(genes, TOSS, PHYSICS)
    assert batch.shape == (5,)
    one = strike_from_genes(genes[3], TOSS, PHYSICS)
    np.testing.assert_allclose(batch[3].p_WR, one.p_WR, atol=1e-15)
    np.testing.assert_allclose(batch[3].v_WR, one.v_WR, atol=1e-15)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        strike_from_genes(np.full(SERVE_GENES, 1.2), TOSS, PHYSICS)
    with pytest.raises(ValueError, match="shape"):
        strike_from_genes(np.zeros(8), TOSS, PHYSICS)


# --- the simulated serve and the umpire -----------------------------------------------------


def test_a_forward_and_slightly_down_strike_is_a_legal_serve():
    outcome = simulate_serve(hand_strike(0.30, (1.0, 0.0, -0.2), (3.5, 0.0, -1.0)), TOSS, PHYSICS)
    assert outcome.impact
    assert outcome.legal, outcome.reason
    assert outcome.reason == "good service"
    assert outcome.service_decision is None
    first, second = [c for c in outcome.contacts if c.kind == ContactKind.TABLE][:2]
    assert -0.5 * PHYSICS.table.length < first.state_pre[0] < 0.0 < second.state_pre[0] < 0.5 * PHYSICS.table.length
    assert outcome.second_bounce is second
    assert outcome.third_contact.kind == ContactKind.FLOOR  # long: off the end
    assert not outcome.short
    assert outcome.decision.reason == "the human did not return the ball: it reached the floor"
    assert 0.0 < outcome.net_clearance < 0.3
    assert outcome.events[0].kind == ContactKind.RACKET and outcome.events[0].time == 0.30
    assert outcome.bounce_speed == pytest.approx(np.linalg.norm(second.state_pre[3:6]))
    assert serve_fitness(outcome, LONG_TOPSPIN) >= 1.0


def test_a_serve_straight_to_the_receivers_court_is_a_fault():
    outcome = simulate_serve(hand_strike(0.30, (1.0, 0.0, 0.3), (3.5, 0.0, 0.5)), TOSS, PHYSICS)
    assert not outcome.legal
    assert outcome.reason == "service touched the receiver's court first"
    assert outcome.service_decision.law == "2.6.3"
    assert outcome.stage == serve.STAGE_OWN_COURT
    assert 0.0 < serve_fitness(outcome, LONG_TOPSPIN) < 0.1


def test_a_racket_that_misses_the_ball_lets_it_fall_to_the_floor():
    outcome = simulate_serve(hand_strike(0.30, (1.0, 0.0, -1.0), (0.1, 0.0, -0.1)), TOSS, PHYSICS)
    assert not outcome.impact
    np.testing.assert_array_equal(outcome.ball_post, outcome.ball_pre)
    assert outcome.reason == "the tossed ball touched the floor before the service"
    assert outcome.stage == serve.STAGE_MISS and outcome.gap > 0.0


def test_a_let_is_not_legal():
    genes = np.random.default_rng(3).uniform(0.0, 1.0, (12, SERVE_GENES))
    lets = [o for o in simulate_serves(strike_from_genes(genes, TOSS, PHYSICS), TOSS, PHYSICS) if o.service_decision and o.service_decision.let]
    assert lets, "the sample should hold a let"
    assert not lets[0].legal and lets[0].stage == serve.STAGE_LET and lets[0].net_clearance <= 0.0


# --- the fitness ----------------------------------------------------------------------------


def test_illegal_fitness_grows_as_the_serve_nears_a_legal_one():
    # Open face, slower and slower: long off the table, then onto the receiver's court first, then
    # into the net, then the server's court twice, then legal.
    outcomes = [simulate_serve(hand_strike(0.30, (1.0, 0.0, 0.3), (vx, 0.0, 0.5)), TOSS, PHYSICS) for vx in (6.0, 5.0, 4.0, 3.5, 3.0, 2.5, 2.0)]
    fitness = [serve_fitness(o, LONG_TOPSPIN) for o in outcomes]
    assert [o.stage for o in outcomes] == [1, 1, 1, 1, 1, 2, 4]
    assert all(0.0 < f < 0.1 for f in fitness[:-1])
    assert np.all(np.diff(fitness) > 0.0)
    miss = simulate_serve(hand_strike(0.30, (1.0, 0.0, -1.0), (0.1, 0.0, -0.1)), TOSS, PHYSICS)
    assert 0.0 < serve_fitness(miss, LONG_TOPSPIN) < fitness[0]


def test_illegal_fitness_stays_inside_its_band_at_the_extremes():
    outcome = simulate_serve(hand_strike(0.30, (1.0, 0.0, 0.3), (6.0, 0.0, 0.5)), TOSS, PHYSICS)
    for stage in range(serve.ILLEGAL_STAGES):
        for gap in (0.0, 1e9, math.inf):
            moved = dataclasses.replace(outcome, stage=stage, gap=gap)
            assert 0.0 < serve_fitness(moved, LONG_TOPSPIN) < 0.1


def test_legal_fitness_is_one_plus_the_weighted_terms():
    outcome = simulate_serve(hand_strike(0.30, (1.0, 0.0, -0.2), (3.5, 0.0, -1.0)), TOSS, PHYSICS)
    assert serve_fitness(outcome, ServeWeights()) == 1.0
    terms = serve.serve_terms(outcome, LONG_TOPSPIN)
    assert all(0.0 <= value <= 1.0 for value in terms.values())
    speed = outcome.bounce_speed
    assert serve_fitness(outcome, ServeWeights(fast=2.0)) == pytest.approx(1.0 + 2.0 * speed / 15.0)
    target = outcome.bounce_position + np.array([0.3, 0.4])
    assert serve_fitness(outcome, ServeWeights(placement=1.0, target=tuple(target))) == pytest.approx(1.5)
    topspin, sidespin = outcome.bounce_spin
    clearance = outcome.net_clearance  # 0.12 m: above the 3 cm margin
    assert terms["low_net"] == pytest.approx(1.0 - (clearance - 0.03) / 0.3)
    assert serve.serve_terms(outcome, ServeWeights(net_margin=2.0 * clearance))["low_net"] == pytest.approx(0.5)
    assert terms["topspin"] == pytest.approx(np.clip(topspin / 300.0, 0.0, 1.0))
    assert terms["backspin"] == pytest.approx(np.clip(-topspin / 300.0, 0.0, 1.0))


def test_spin_components_name_topspin_backspin_and_sidespin():
    state = np.zeros(9)
    state[3] = 5.0  # towards the human
    state[7] = 100.0  # about +y: the ball's top moves forward
    np.testing.assert_allclose(serve.spin_components(state), [100.0, 0.0])
    state[3], state[4] = 0.0, 5.0  # travelling along +y, topspin is about -x
    state[6], state[7] = -100.0, 0.0
    np.testing.assert_allclose(serve.spin_components(state), [100.0, 0.0])
    state[8] = 40.0
    assert serve.spin_components(state)[1] == 40.0


def test_serve_kinds_and_weights_are_checked():
    assert {"short_backspin", "long_topspin", "long_sidespin", "fast_long"} <= set(SERVE_KINDS)
    with pytest.raises(ValueError, match="short_backspin, long_topspin, long_sidespin, fast_long"):
        serve.serve_weights("lob")
    with pytest.raises(ValueError, match="fast"):
        ServeWeights(fast=-1.0)


# --- batching -------------------------------------------------------------------------------


def test_the_batched_simulation_equals_one_serve_at_a_time():
    genes = np.random.default_rng(3).uniform(0.0, 1.0, (12, SERVE_GENES))
    fitness, batch = serve.evaluate_genes(genes, TOSS, PHYSICS, LONG_TOPSPIN)
    assert len({o.reason for o in batch}) >= 3  # a varied sample: legal serves and faults
    for row, outcome in zip(genes, batch):
        one = simulate_serve(strike_from_genes(row, TOSS, PHYSICS), TOSS, PHYSICS)
        assert (one.legal, one.reason, one.stage) == (outcome.legal, outcome.reason, outcome.stage)
        np.testing.assert_array_equal(one.ball_post, outcome.ball_post)
        assert [(c.kind, c.time) for c in one.contacts] == [(c.kind, c.time) for c in outcome.contacts]
        for mine, theirs in zip(one.contacts, outcome.contacts):
            np.testing.assert_array_equal(mine.state_pre, theirs.state_pre)
        assert serve_fitness(one, LONG_TOPSPIN) == serve_fitness(outcome, LONG_TOPSPIN)
    assert fitness.shape == (12,)


def test_mirroring_y_mirrors_the_serve():
    genes = np.array([0.5, 0.6, 0.2, 0.5, 0.6, 0.8, 0.5, 0.5, 0.5])
    mirrored_toss = TossState(position=TOSS.position * [1.0, -1.0, 1.0])
    mirrored_genes = genes.copy()
    mirrored_genes[[2, 5]] = 1.0 - genes[[2, 5]]  # azimuth and side brushing change sign
    outcome = simulate_serve(strike_from_genes(genes, TOSS, PHYSICS), TOSS, PHYSICS)
    mirror = simulate_serve(strike_from_genes(mirrored_genes, mirrored_toss, PHYSICS), mirrored_toss, PHYSICS)
    assert (outcome.legal, outcome.reason) == (mirror.legal, mirror.reason)
    flip = np.array([1, -1, 1, 1, -1, 1, -1, 1, -1])  # p, v mirror; spin is a pseudovector
    for mine, theirs in zip(outcome.contacts, mirror.contacts):
        assert mine.kind == theirs.kind
        np.testing.assert_allclose(mine.state_pre * flip, theirs.state_pre, atol=1e-9)
