"""The controller's core without ROS (sep_control.control.controllers and .loop), and the
whole closed loop of the node graph stepped in plain Python with the same core objects the
nodes run: PlantEpisode (the plant node's), EstimatorCore (the estimator's), ControlLoopCore +
Controller (the lqr's); its inputs equal the offline Monte Carlo's for that run."""
import numpy as np
import pytest

from core_helpers import flat
from sep_control.control.controllers import (CONTROLLER_NAMES, Controller, LqrLaw, MpcLaw, MpcOptions, OpenLoop,
                                             make_controller, resolve_controller_name)
from sep_control.control.loop import ControlLoopCore
from sep_control.control.mpc import MPCStats, RomMPC
from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.evaluation.montecarlo import simulate
from sep_estimator.estimator_core import EstimatorCore
from sep_plant import topics
from sep_plant.plant_episode import PlantEpisode

SMALL = dict(n_x=20, n_steps=40, k_band=24, lqr_k_switch=20)
FAST = dict(p=5, q=5, n_r=10, ensemble=20, belief_iter=1)


@pytest.fixture(scope="module")
def limited():
    """A design whose input limits bind (the MPC solves QPs, the LQR command is clipped)."""
    sc = flat(**SMALL, u_min=0.0, u_max=0.6)
    return sc, run_design(sc.plant, sc.problem, DesignSettings(**FAST), show_progress=False, log=lambda m: None)


def laws(sc, d, horizon=6):
    return {name: make_controller(name, d.lqg, sc.problem, d.nominal.u, MpcOptions(horizon=horizon))
            for name in ("open_loop", "rom_lqg", "rom_mpc")}


def test_factory_names_and_aliases(limited):
    sc, d = limited
    made = laws(sc, d)
    assert isinstance(made["open_loop"], OpenLoop) and isinstance(made["rom_lqg"], LqrLaw)
    assert isinstance(made["rom_mpc"], MpcLaw) and made["rom_mpc"].horizon == 6
    oracle = make_controller("oracle_lqg", d.lqg, sc.problem, d.nominal.u)
    assert isinstance(oracle, LqrLaw) and oracle.name == "oracle_lqg"
    for law in (*made.values(), oracle):
        # the laws read the filter's whole state z = [a; d] (the design has disturbance states)
        assert isinstance(law, Controller) and law.name in CONTROLLER_NAMES and law.n == d.n_r + d.lqg.n_d
    with pytest.raises(ValueError, match="unknown controller 'pid'"):
        make_controller("pid", d.lqg, sc.problem, d.nominal.u)
    assert resolve_controller_name("rom_mpc") == ("rom_mpc", None)
    assert resolve_controller_name("lqr") == ("rom_lqg", "lqr")
    assert resolve_controller_name("mpc", ("rom_lqg", "rom_mpc")) == ("rom_mpc", "mpc")
    with pytest.raises(ValueError, match="must be 'rom_lqg' or 'rom_mpc', got 'oracle_lqg'"):
        resolve_controller_name("oracle_lqg", ("rom_lqg", "rom_mpc"))


def test_laws_batch_equals_one_by_one_and_stay_in_the_limits(limited):
    """A batch of estimates (the Monte Carlo) gives each run the input a single estimate (a node)
    gets; the MPC keeps each run's warm start, as separate controllers of one run each do."""
    sc, d = limited
    lo, hi = sc.problem.limits(d.info.n_u)
    rng = np.random.default_rng(3)
    A = 2.0 * rng.standard_normal((d.n_steps, 4, d.lqg.model.n))
    batch = laws(sc, d)
    singles = [laws(sc, d) for _ in range(4)]
    for k in range(d.n_steps):
        for name, law in batch.items():
            U = law.command(k, A[k])
            assert U.shape == (4, d.info.n_u) and np.all(U >= lo) and np.all(U <= hi)
            for r in range(4):
                np.testing.assert_allclose(singles[r][name].command(k, A[k, r]), U[r], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(batch["open_loop"].command(3, A[3]), np.tile(np.clip(d.nominal.u[3], lo, hi), (4, 1)))
    np.testing.assert_array_equal(batch["rom_lqg"].command(5, A[5, 0]),
                                  np.clip(d.nominal.u[5] + d.lqg.K[5] @ A[5, 0], lo, hi))
    assert batch["rom_mpc"].stats.qp > 0
    merged = MPCStats.merged([s["rom_mpc"].stats for s in singles]).as_dict()
    assert merged["mpc_qp_steps"] == batch["rom_mpc"].stats.qp and merged["mpc_horizon"] == 6
    assert merged["mpc_unconstrained_steps"] == batch["rom_mpc"].stats.unconstrained


def test_mpc_law_is_the_rom_mpc_with_shifted_warm_starts(limited):
    sc, d = limited
    rng = np.random.default_rng(4)
    law = make_controller("rom_mpc", d.lqg, sc.problem, d.nominal.u, {"horizon": 6})
    ref = RomMPC(d.lqg, sc.problem, d.nominal.u, horizon=6)
    warm = None
    for k in range(d.n_steps):
        a = 2.0 * rng.standard_normal(d.lqg.model.n)
        u_ref, z = ref.command(k, a, warm)
        warm = ref.shift(z)
        np.testing.assert_array_equal(law.command(k, a), u_ref)
    got, want = law.stats.as_dict(), ref.stats.as_dict()
    assert got["mpc_qp_steps"] > 0
    for key in ("mpc_horizon", "mpc_unconstrained_steps", "mpc_qp_steps", "mpc_fallbacks", "mpc_fallback_reasons"):
        assert got[key] == want[key], key


def test_a_law_reads_the_leading_entries_of_a_longer_estimate(limited):
    """Entries appended to the filter state z = [a_hat; d_hat] leave these laws as they are:
    they read z, the first n entries."""
    sc, d = limited
    rng = np.random.default_rng(5)
    a = rng.standard_normal((3, d.lqg.model.n))
    z = np.concatenate([a, rng.standard_normal((3, 2))], axis=1)
    for name in ("open_loop", "rom_lqg", "rom_mpc"):
        np.testing.assert_array_equal(laws(sc, d)[name].command(7, z), laws(sc, d)[name].command(7, a))


def test_loop_core_commands_fallbacks_and_late_estimates(limited):
    sc, d = limited
    N = d.n_steps
    lo, hi = sc.problem.limits(d.info.n_u)
    law = make_controller("rom_lqg", d.lqg, sc.problem, d.nominal.u)
    core = ControlLoopCore(law, d.nominal.u, lo, hi)
    a = np.full(d.lqg.model.n, 0.1)
    # step 0: the measurement arms the watchdog, the estimate gives the command
    assert core.measurement(0) is True
    out = core.estimate(0, a)
    np.testing.assert_array_equal(out.u, law.command(0, a))
    assert not (out.late or out.end or out.fallback) and core.timeout() is None
    assert core.measurement(0) is False                      # not new
    # step 1: no estimate in time -> the nominal input, clipped; the estimate then is late
    assert core.measurement(1) is True
    out = core.timeout()
    assert out.fallback and out.k == 1
    np.testing.assert_array_equal(out.u, np.clip(d.nominal.u[1], lo, hi))
    assert core.timeout() is None
    late = core.estimate(1, a)
    assert late.late and late.u is None
    # step 2: the estimate comes before the measurement: sent; the measurement arms nothing
    assert core.estimate(2, a).u is not None and core.measurement(2) is False
    # the last step: no command; its estimate (or the watchdog) ends the episode
    assert core.measurement(N) is True and not core.done
    assert core.timeout().end and core.done
    assert core.counters() == {"commands": 2, "fallbacks": 1, "late_estimates": 1}
    assert core.fallback_steps == [1] and core.last_k == N
    assert core.measurement(N + 1) is False and core.measurement(-1) is False
    other = ControlLoopCore(law, d.nominal.u, lo, hi)
    assert other.estimate(N, a).end and other.done


class Graph:
    """plant node + estimator + lqr as in ROS, in plain Python: the episode's `wait` delivers the
    command the estimator and the controller core compute from the measurement just sent."""

    def __init__(self, d, law, episode):
        self.d, self.ep = d, episode
        self.est = EstimatorCore(d.lqg, d.nominal.u, d.nominal.y, d.nominal.field)
        self.core = ControlLoopCore(law, d.nominal.u, *d.problem.limits(d.info.n_u))
        self.y = None
        self.U = []

    # the sink of the plant episode
    def clock(self, k):
        pass

    def measurement(self, k, y):
        self.y = (k, y)

    def applied(self, k, u):
        self.U.append(u)
        self.est.applied(k, u)

    def field(self, k, f):
        pass

    def deadline_miss(self, k, period):
        raise AssertionError(f"deadline miss at step {k} in lockstep")

    def wait(self, t_end, done):
        k, y = self.y
        a, rej = self.est.measurement(k, y)
        assert rej is None
        out = self.core.estimate(k, a)
        self.est.finish_step()
        stamp = topics.stamp_ns(k, self.d.info.dt)
        assert self.ep.command(stamp, list(self.d.info.input_names), out.u) is None
        return done()


@pytest.mark.parametrize("name", ["rom_lqg", "rom_mpc"])
def test_node_graph_cores_in_a_plain_loop_equal_the_monte_carlo(limited, name):
    sc, d = limited
    seed, run = 7, 3
    law = make_controller(name, d.lqg, sc.problem, d.nominal.u, MpcOptions(horizon=6))
    ep = PlantEpisode(sc.plant, sc.problem, seed=seed, run=run, keep_trajectory=True)
    g = Graph(d, law, ep)
    ep.run(g.wait, g)
    ref = simulate(sc.plant, d, name, seed, range(run, run + 1), mpc={"horizon": 6})
    U = np.array(g.U)
    assert np.max(np.abs(U - ref.U[0])) <= 1e-12
    assert np.max(np.abs(ep.F - ref.F[0])) <= 1e-12 and np.max(np.abs(ep.Y - ref.Y[0])) <= 1e-12
    assert g.core.counters() == {"commands": d.n_steps, "fallbacks": 0, "late_estimates": 0}
    if name == "rom_mpc":
        assert law.stats.qp > 0 and law.stats.qp == ref.summary["mpc_qp_steps"]
