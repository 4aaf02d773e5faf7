"""A controlgym plant over topics: a lockstep episode (plant node + lqg) equals the offline
closed loop of the same seed and run to 1e-9, starting from that run's own draw of the env's
random initial state."""
import importlib.util

import numpy as np
import pytest

from node_harness import _cached_case, launcher, probe  # noqa: F401
from test_loop_equivalence import check_equivalence, run_episode

pytestmark = [pytest.mark.ros,
              pytest.mark.skipif(importlib.util.find_spec("controlgym") is None,
                                 reason="controlgym is not installed (make venv installs it: requirements-controlgym.txt)")]

CONTROLGYM_YAML = """\
# controlgym's Burgers env (n_state 32), its noise off in the plant, 4 process-noise modes
plant:
  type: controlgym
  env: burgers
  n_state: 32
  n_steps: 20
  process_noise_cov: 1.0e-5
  sensor_noise_cov: 0.05
  noise_modes: 4
  mean_samples: 100
n_steps: 20
target: "0.1 * cos(2 * pi * x)"
band: 1.0
band_window: [1, 20]
q_outside: 1.0
r_u: 0.03125
w_std: 0.0031622776601683794
v_std: 0.22360679774997896
lqr_k_switch: 0
lqr_q_early: 1.0
lqr_r: 0.03125
u_init: 0.0
"""

FAST = {"p": 4, "q": 4, "n_r": 6, "ensemble": 20, "belief_iter": 1, "max_iter": 4}


@pytest.fixture(scope="module")
def controlgym_case(tmp_path_factory):
    return _cached_case(tmp_path_factory, "controlgym", yaml_text=CONTROLGYM_YAML, settings=FAST)


def test_controlgym_lockstep_over_topics_equals_offline(launcher, probe, controlgym_case, tmp_path):
    from sep_plant.initial import initial_states

    case = controlgym_case
    assert case.scenario.plant_type == "controlgym"
    x0 = initial_states(case.plant, 2, [4])[0]
    assert not np.allclose(x0, case.plant.initial_state(1)[0])     # the run starts off the nominal
    pr, summary = run_episode(launcher, probe, case, tmp_path, three=False, seed=2, run=4)
    assert summary["status"] == "completed"
    check_equivalence(pr, case, 2, 4)
