"""`sep analyze` of a sim-to-real rehearsal bag: the plant ran with other plant keys and a
perturbation (its scenario message carries both), the controllers with allow_model_mismatch
(their /diagnostics carry model_mismatch): the analysis measures the episode against the
design's goal and names the differences (a line in the report, ``model_mismatch`` in the JSON)."""
import json

import pytest

from bag_synth import T0_NS, diagnostics, episode_messages, fake_design, small_scenario, synthetic_episode, \
    write_messages
from sep_control.bags.analysis import AnalysisError, analyze
from sep_control.cli.main import main as sep
from sep_estimator.design_file import save_design
from sep_plant import topics as T
from sep_plant.scenario import scenario_payload

EXPECTED = ["plant.t_right: 150.0 -> 147.0", "input_gain: 0.8"]


@pytest.fixture(scope="module")
def rehearsal(tmp_path_factory):
    d = tmp_path_factory.mktemp("rehearsal")
    model_ep = synthetic_episode(small_scenario(), seed=0)
    dpath = save_design(d / "design.npz", fake_design(model_ep))
    truth = small_scenario(t_right=147.0)
    ep = synthetic_episode(truth, seed=1)
    ep.payload = scenario_payload(truth, ep.info, {"input_gain": [0.8] * ep.info.n_u})
    msgs = episode_messages(ep)
    reported = diagnostics(T0_NS, {"model_mismatch": json.dumps(EXPECTED)}, 0, name="/sep/lqr")
    with_report = write_messages(d / "rehearsal_bag", msgs + [(T.DIAGNOSTICS, T0_NS + 1, bytes(reported))])
    without = write_messages(d / "unreported_bag", msgs)
    return d, dpath, ep, with_report, without


def test_rehearsal_bag_is_measured_against_the_designs_goal(rehearsal):
    d, dpath, ep, bag, without = rehearsal
    rep = analyze(bag, dpath)
    assert rep.model_mismatch == EXPECTED and rep.metrics["model_mismatch"] == EXPECTED
    assert rep.mismatch == [] and "scenario_mismatch" not in rep.metrics
    assert rep.episode.perturbation == {"input_gain": [0.8] * ep.info.n_u}
    obj = rep.design.objective
    assert rep.objective is obj and rep.F_nom is rep.design.nominal.field      # the design's goal
    # without the controllers' report it is a scenario mismatch, as before
    with pytest.raises(AnalysisError, match=r"another scenario.*plant\.t_right"):
        analyze(without, dpath)
    flagged = analyze(without, dpath, allow_mismatch=True)
    assert flagged.mismatch == ["plant.t_right: 150.0 != 147.0"] and flagged.model_mismatch == EXPECTED
    # no design: what the controllers reported
    assert analyze(bag).metrics["model_mismatch"] == EXPECTED


def test_analyze_cli_names_the_mismatch(rehearsal, tmp_path, capsys):
    d, dpath, ep, bag, _ = rehearsal
    out, js = tmp_path / "rep", tmp_path / "m.json"
    assert sep(["analyze", str(bag), "--design", str(dpath), "--out", str(out), "--json", str(js),
                "--no-figures", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "model_mismatch: rehearsal_bag: the design ran on another plant than its model: " \
           "plant.t_right: 150.0 -> 147.0; input_gain: 0.8" in text
    assert json.loads(js.read_text())[0]["model_mismatch"] == EXPECTED
    md = (out / "report.md").read_text()
    assert "Model mismatch (the design ran on another plant than its model): plant.t_right: 150.0 -> 147.0; " \
           "input_gain: 0.8" in md


def test_scenario_and_perturbation_come_from_one_message(rehearsal, tmp_path):
    """The scenario topic is read in one pass: a later scenario message whose perturbation does
    not parse is noted once and skipped whole, so scenario and perturbation stay the earlier
    message's (never one message's scenario with another's perturbation)."""
    from bag_synth import string
    from sep_control.bags.reader import read_episode

    d, dpath, ep, bag, _ = rehearsal
    data = json.loads(ep.payload)
    data["perturbation"] = {"input_gain": "not a number"}
    data["scenario"]["plant"]["t_right"] = 140.0
    bad = (T.topic_name(T.SCENARIO), T0_NS + 2, bytes(string(json.dumps(data))))
    e = read_episode(write_messages(tmp_path / "bag", episode_messages(ep) + [bad]))
    unreadable = [n for n in e.notes if "unreadable" in n]
    assert len(unreadable) == 1 and "message unreadable" in unreadable[0] and "input_gain" in unreadable[0], e.notes
    assert e.scenario == ep.scenario and e.scenario.plant_config["t_right"] == 147.0
    assert e.perturbation == {"input_gain": [0.8] * ep.info.n_u}
