"""The plant node's episode without ROS (sep_plant.plant_episode.PlantEpisode), on a simulated clock:
lockstep order and numbers, the command gate (every rejection reason, counted), real-time
ticks with deadline misses and the held input, the lockstep timeout."""
import numpy as np
import pytest

from core_helpers import flat
from sep_plant import gate, topics
from sep_plant.plant_episode import CommandTimeout, PlantEpisode
from sep_plant.noise import DEFAULT_SEED, noise_sequences
from sep_plant.protocol import fields, rollout

SMALL = dict(n_x=20, n_steps=40, k_band=24, lqr_k_switch=20)


@pytest.fixture(scope="module")
def scenario():
    return flat(**SMALL, u_min=0.0, u_max=2.0)


class Loop:
    """A simulated clock, a scripted controller and a recording sink.

    `script(k)` gives the messages sent in answer to measurement k: (delay after it, step of
    the stamp or None for a stamp of `ns`, names, values[, ns]). `wait` delivers the queued
    messages that arrive by its end time in order, advancing the clock to each."""

    def __init__(self, scenario, script, **episode):
        self.t = 0.0
        self.ep = PlantEpisode(scenario.plant, scenario.problem, clock=lambda: self.t, **episode)
        self.script = script
        self.queue: list[tuple] = []
        self.events: list[tuple] = []
        self.misses: list[int] = []

    def clock(self, k):
        self.events.append(("clock", k))

    def measurement(self, k, y):
        self.events.append(("y", k))
        for msg in self.script(k):
            delay, step, names, values, *ns = msg
            stamp = topics.stamp_ns(step, self.ep.dt) if step is not None else ns[0]
            self.queue.append((self.t + delay, stamp, names, values))
        self.queue.sort(key=lambda m: m[0])

    def applied(self, k, u):
        self.events.append(("u", k, np.array(u)))

    def field(self, k, f):
        self.events.append(("field", k, f()))

    def deadline_miss(self, k, period):
        self.misses.append(k)

    def wait(self, t_end, done):
        while self.queue and self.queue[0][0] <= t_end and not done():
            t, stamp, names, values = self.queue.pop(0)
            self.t = max(self.t, t)
            self.ep.command(stamp, names, values)
        if not done():
            self.t = max(self.t, t_end)
        return done()

    def run(self):
        self.ep.run(self.wait, self)
        return self

    def applied_inputs(self):
        return np.array([e[2] for e in self.events if e[0] == "u"])


def u_of(k, n_u):
    return np.full(n_u, 0.1 * (k + 1))


def test_lockstep_order_numbers_and_limits(scenario):
    """Per step: clock, y_k, (command) u_k, field_k; y and the field are the plant's with the
    noise of (seed, run); the command is clipped to the limits."""
    n_u, N = scenario.plant.n_u, scenario.problem.n_steps
    ask = lambda k: u_of(k, n_u) * (1.0 if k % 7 else 30.0)        # every 7th beyond u_max
    names = list(scenario.plant.input_names)
    lp = Loop(scenario, lambda k: [(0.01, k, names, ask(k))] if k < N else [], seed=5, run=2,
              keep_trajectory=True).run()
    kinds = [e[:2] for e in lp.events]
    expect = [x for k in range(N) for x in (("clock", k), ("y", k), ("u", k), ("field", k))]
    assert kinds == expect + [("clock", N), ("y", N), ("field", N)]
    U = lp.applied_inputs()
    np.testing.assert_array_equal(U, np.clip([ask(k) for k in range(N)], 0.0, 2.0))
    assert U.max() == 2.0
    w, v = noise_sequences(scenario.problem, lp.ep.info, 5, [2])
    X = rollout(scenario.plant, scenario.plant.initial_state(1), U, w)
    np.testing.assert_array_equal(lp.ep.trajectory(N)["F"], fields(scenario.plant, X)[0])
    np.testing.assert_array_equal(np.array([e[2] for e in lp.events if e[0] == "field"]), lp.ep.F)
    y = scenario.plant.observe(X[0]) + v[0]
    np.testing.assert_array_equal(lp.ep.Y, y)
    np.testing.assert_allclose(lp.ep.latencies(), 0.01, rtol=1e-9)
    assert lp.ep.k == N and lp.ep.deadline_misses == 0 and lp.ep.rejections.total == 0


def test_every_bad_command_is_rejected_for_its_reason_and_counted(scenario):
    """At step 2 the controller sends one bad command of each kind before the good one, and a
    second good one after it: each is refused for its reason and the good one is applied."""
    n_u, N = scenario.plant.n_u, scenario.problem.n_steps
    dt_ns = topics.dt_ns(scenario.plant.dt)
    good = lambda k: 0.1 * u_of(k, n_u)
    names = list(scenario.plant.input_names)

    def script(k):
        if k >= N:
            return []
        msgs = [(0.001, k, names, good(k))]
        if k == 2:
            bad = [(0.001, 2, names, np.r_[np.nan, good(2)[1:]]),           # non_finite
                   (0.001, 2, names[:-1], good(2)[:-1]),                     # wrong_length
                   (0.001, 2, ["x"] + names[1:], good(2)),                   # unknown_names
                   (0.001, 2, names[:1] * n_u, good(2)),                     # bad_names (duplicated)
                   (0.001, 0, names, good(0)),                               # stale
                   (0.001, 3, names, good(3)),                               # ahead
                   (0.001, N, names, good(N)),                               # beyond_horizon
                   (0.001, None, names, good(2), 2 * dt_ns + dt_ns // 2)]    # bad_stamp
            msgs = bad + msgs + [(0.002, 2, names, 9 * good(2))]             # duplicate (after the good one)
        return msgs

    lp = Loop(scenario, script).run()
    np.testing.assert_array_equal(lp.applied_inputs(), [good(k) for k in range(N)])
    rej = lp.ep.rejections
    assert rej.as_dict() == {gate.NON_FINITE: 1, gate.WRONG_LENGTH: 1, gate.UNKNOWN_NAMES: 1, gate.BAD_NAMES: 1,
                             gate.BAD_STAMP: 1, gate.BEYOND_HORIZON: 1, gate.STALE: 1, gate.DUPLICATE: 1,
                             gate.AHEAD: 1}
    assert rej.last.category == gate.DUPLICATE and 'step 2' in rej.last.detail


def test_realtime_ticks_misses_and_the_held_input(scenario):
    """A tick every dt / real_time_factor: an answer after its tick is a deadline miss (the held
    input goes out; the late command is then refused as stale); after the controller goes silent
    the last input is held to the end; zeros before the first command."""
    n_u, N = scenario.plant.n_u, scenario.problem.n_steps
    period = scenario.plant.dt / 5.0
    names = list(scenario.plant.input_names)

    def script(k):
        if k == 0 or k >= 10:
            return []                                        # no command of step 0; silent from 10
        return [(1.5 * period if k == 4 else 0.2 * period, k, names, u_of(k, n_u))]

    lp = Loop(scenario, script, mode="realtime", real_time_factor=5.0).run()
    U = lp.applied_inputs()
    np.testing.assert_array_equal(U[0], np.zeros(n_u))                   # nothing applied yet: zeros
    np.testing.assert_array_equal(U[4], U[3])                             # missed: held
    for k in (1, 2, 3, 5, 6, 7, 8, 9):
        np.testing.assert_array_equal(U[k], u_of(k, n_u))
    np.testing.assert_array_equal(U[10:], np.tile(u_of(9, n_u), (N - 10, 1)))
    assert lp.misses == [0, 4] + list(range(10, N)) and lp.ep.deadline_misses == len(lp.misses)
    assert lp.ep.rejections.as_dict() == {gate.STALE: 1}                  # command 4, at step 5
    np.testing.assert_allclose(lp.ep.t_pub, np.arange(N + 1) * period, rtol=0, atol=1e-12)
    assert lp.ep.period == pytest.approx(period)


def test_lockstep_timeout_names_the_step_and_the_last_rejection(scenario):
    n_u, names = scenario.plant.n_u, list(scenario.plant.input_names)
    lp = Loop(scenario, lambda k: [] if k else [(0.1, 0, names, np.full(n_u, np.inf))],
              command_timeout_s=1.0)
    with pytest.raises(CommandTimeout) as err:
        lp.run()
    msg = str(err.value)
    assert 'no valid command stamped step 0 (t = 0 s) within command_timeout_s = 1 s' in msg
    assert '1 command(s) rejected, last: non_finite' in msg and err.value.exit_code == 3
    assert lp.ep.k == 0 and lp.t == pytest.approx(1.0)


def test_bad_mode_and_defaults(scenario):
    with pytest.raises(ValueError, match="mode must be one of"):
        PlantEpisode(scenario.plant, scenario.problem, mode="fast")
    ep = PlantEpisode(scenario.plant, scenario.problem)
    w, v = noise_sequences(scenario.problem, ep.info, DEFAULT_SEED, [0])
    np.testing.assert_array_equal(ep.w, w[0])
    assert DEFAULT_SEED == 1 and ep.mode == "lockstep" and ep.F is None
    with pytest.raises(ValueError, match="keep_trajectory"):
        ep.trajectory(3)
