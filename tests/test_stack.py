"""The control stack's batch of proposals: ``ControlStack.propose_batch`` gives, env by env, what
a loop of ``propose`` gives (accepted or not, the same reason, the same plans to 1e-9), on random
invariant starts, starts outside the invariant set and actions whose QP bounds bind."""

import numpy as np
import pytest

from ace_drake.control.params import ControlParams
from ace_drake.control.stack import make_control_stack, random_invariant_state
from ace_drake.robot.params import RobotScenario


@pytest.fixture(scope="module")
def stack():
    return make_control_stack(RobotScenario(), ControlParams())


class CountingDaqp:
    """A stand-in for the QP's DAQP workspace that counts its solves (the joints whose bounds bind)."""

    def __init__(self, model):
        self.model, self.solves = model, 0

    def update(self, **kwargs):
        self.model.update(**kwargs)

    def solve(self):
        self.solves += 1
        return self.model.solve()


def starts_and_actions(stack, rng, count):
    """Random invariant starts (every fifth pushed outside the invariant set: a joint at full
    speed just short of its limit) and actions: uniform in the box, and corners every third."""
    limits = stack.limits
    q, v, a = (np.array(x) for x in zip(*(random_invariant_state(stack, rng) for _ in range(count))))
    for row in range(0, count, 5):
        joint = rng.integers(8)
        v[row, joint] = limits.velocity[joint]
        q[row, joint] = limits.upper[joint] - 1e-3
    actions = rng.uniform(-1.0, 1.0, (count, 16))
    actions[::3] = np.sign(actions[::3])
    return q, v, a, actions


def assert_same_trajectory(got, expected, name):
    assert (got is None) == (expected is None), name
    if expected is not None:
        assert got.q.shape == expected.q.shape, name
        for field in ("q", "v", "a"):
            np.testing.assert_allclose(getattr(got, field), getattr(expected, field), rtol=0, atol=1e-9, err_msg=name)


def assert_batch_is_the_loop(stack, q, v, a, actions):
    batch = stack.propose_batch(q, v, a, actions)
    assert len(batch) == q.shape[0]
    for row in range(q.shape[0]):
        expected = stack.propose(q[row], v[row], a[row], actions[row])
        got = batch.proposal(row)
        assert (got.safe, got.reason) == (expected.safe, expected.reason), row
        assert got.decision.accepted == expected.decision.accepted and got.decision.reason == expected.decision.reason
        assert (got.target is None) == (expected.target is None), row
        if expected.target is not None:
            np.testing.assert_array_equal(np.stack(got.target), np.stack(expected.target))
        for name in ("plan", "segment", "reset"):
            assert_same_trajectory(getattr(got, name), getattr(expected, name), f"{name} of row {row}")
    return batch


def test_propose_batch_is_a_loop_of_propose(stack, monkeypatch):
    q, v, a, actions = starts_and_actions(stack, np.random.default_rng(7), 120)
    daqp = CountingDaqp(stack.qp._daqp)
    monkeypatch.setattr(stack.qp, "_daqp", daqp)
    batch = assert_batch_is_the_loop(stack, q, v, a, actions)
    assert daqp.solves > 0  # rows whose bounds bind reached DAQP
    reasons = {reason.split(":")[0] for reason in batch.reason}
    assert {"", "infeasible start"} <= reasons, reasons
    assert np.all(np.isnan(batch.target_q[~batch.mapped])) and not np.any(np.isnan(batch.target_q[batch.mapped]))


def test_a_batch_of_one_is_propose(stack):
    q, v, a, actions = starts_and_actions(stack, np.random.default_rng(8), 2)
    for row in range(2):  # an infeasible start (row 0) and a random one
        assert_batch_is_the_loop(stack, q[row : row + 1], v[row : row + 1], a[row : row + 1], actions[row : row + 1])


def test_bad_batches_raise(stack):
    q, v, a, actions = starts_and_actions(stack, np.random.default_rng(9), 3)
    with pytest.raises(ValueError, match="propose_batch"):
        stack.propose_batch(q, v, a, actions[:2])
    with pytest.raises(ValueError, match="propose_batch"):
        stack.propose_batch(q[0], v[0], a[0], actions[0])


def test_an_initial_plan_from_the_same_state_is_looked_up_and_cannot_be_changed(stack):
    rng = np.random.default_rng(3)
    q, v, a = random_invariant_state(stack, rng)
    plan, free = stack.initial_plan(q, v, a)
    again, free_again = stack.initial_plan(q.copy(), v.copy(), a.copy())
    assert again is plan and free_again == free
    with pytest.raises(ValueError):
        plan.q[0, 0] = 1.0  # shared between callers: read-only
    original = stack.reset_pose
    try:
        stack.reset_pose = original + 0.01  # another reset target: the cached plan no longer holds
        other, _ = stack.initial_plan(q, v, a)
    finally:
        stack.reset_pose = original
    assert other is not plan and not np.array_equal(other.q[-1], plan.q[-1])
    assert stack.initial_plan(q, v, a)[0] is plan
