"""A design as a Gymnasium policy: ``reset()`` and ``act(observation) -> action``.

`DesignPolicy` runs a design file's estimator and control law against any env a user has, one
episode at a time, on the same cores as the nodes and the Monte Carlo: the Kalman filter of
`sep_estimator.estimator_core.EstimatorCore` and a law of
`sep_control.control.controllers.make_controller` (rom_lqg, rom_mpc, open_loop)::

    policy = DesignPolicy.from_file("out/burgers.npz", observation_lag=1)
    obs, info = env.reset(seed=0)
    policy.reset()
    for k in range(policy.horizon):
        obs, reward, terminated, truncated, info = env.step(policy.act(obs))

Observation timing (`observation_lag`):

* 0: the observation passed at call k measures the state of step k (y_k = h(x_k) + v_k): the
  filter updates with it and the law commands from zhat_{k|k}, as in the nodes.
* 1: the env returns, with ``step(u_k)``, the measurement of x_k taken before the update, so call
  k (k >= 1) receives a measurement of step k-1 (controlgym's envs). Call 0 gets the reset's
  y_0: the filter updates with it and commands from zhat_{0|0}. Call 1 gets a second
  measurement of x_0, which is dropped (the filter takes one measurement per step). Call k >= 2
  updates step k-1 with its observation, predicts with u_{k-1} and commands from the predicted
  estimate zhat_{k|k-1} (`EstimatorCore.predicted`).

The actions are the law's (clipped to the design's input limits). Pure numpy: no ROS import.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from sep_estimator.design import Design
from sep_estimator.estimator_core import EstimatorCore

from sep_control.control.controllers import MpcOptions, make_controller

POLICY_CONTROLLERS = ("rom_lqg", "rom_mpc", "open_loop")


class DesignPolicy:
    """The design's LQG (or MPC) as a policy for one env episode at a time.

    Parameters
    ----------
    design : Design
        A design (`sep_estimator.design_file.load_design`, or `run_design`'s result).
    controller : str
        'rom_lqg', 'rom_mpc' or 'open_loop'.
    observation_lag : int
        0 or 1 (module docstring).
    mpc : MpcOptions or dict, optional
        Options of rom_mpc.
    """

    def __init__(self, design: Design, controller: str = "rom_lqg", observation_lag: int = 0,
                 mpc: MpcOptions | dict | None = None):
        if controller not in POLICY_CONTROLLERS:
            raise ValueError(f"controller must be one of {', '.join(POLICY_CONTROLLERS)}, got {controller!r}")
        if observation_lag not in (0, 1):
            raise ValueError(f"observation_lag must be 0 or 1, got {observation_lag!r}")
        self.design, self.controller, self.observation_lag = design, controller, int(observation_lag)
        nom = design.nominal
        self.law = make_controller(controller, design.lqg, design.problem, nom.u, mpc)
        self.horizon = int(nom.u.shape[0])
        self.n_y = int(nom.y.shape[1])
        self.reset()

    @classmethod
    def from_file(cls, path: str | Path, **kwargs) -> "DesignPolicy":
        """The policy of a design file (`sep_estimator.design_file.load_design`)."""
        from sep_estimator.design_file import load_design

        return cls(load_design(path), **kwargs)

    def reset(self) -> None:
        """A new episode: the filter at its prior, no warm starts."""
        nom = self.design.nominal
        self.core = EstimatorCore(self.design.lqg, nom.u, nom.y, nom.field)
        if hasattr(self.law, "reset"):
            self.law.reset()
        self.k = 0
        self.last_u: np.ndarray | None = None

    def act(self, observation: np.ndarray) -> np.ndarray:
        """The action of the next step from the env's observation.

        Parameters
        ----------
        observation : ndarray, shape (n_y,)
            The env's observation (its timing: `observation_lag`).

        Returns
        -------
        ndarray, shape (n_u,)
            u_k.
        """
        k = self.k
        if k >= self.horizon:
            raise ValueError(f"the design's horizon is {self.horizon} steps; call reset() for a new episode")
        y = np.asarray(observation, dtype=float).ravel()
        if y.size != self.n_y:
            raise ValueError(f"observation has {y.size} entries, the design has {self.n_y} outputs")
        if self.observation_lag == 0 or k == 0:
            est = self._measure(k, y)
        else:
            if k >= 2:
                self._measure(k - 1, y)
            self.core.applied(k - 1, self.last_u)
            est = self.core.predicted(k)
        u = np.asarray(self.law.command(k, est), dtype=float)
        if self.observation_lag == 0:
            self.core.applied(k, u)
        self.last_u = u
        self.k = k + 1
        return u.copy()

    def _measure(self, k: int, y: np.ndarray) -> np.ndarray:
        est, rej = self.core.measurement(k, y)
        if rej is not None:
            raise ValueError(f"measurement of step {k} refused: {rej}")
        return est
