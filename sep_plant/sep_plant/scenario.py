"""Scenario: one plant (its type and its own keys) and one control problem, from YAML.

A scenario file has a ``plant:`` section (``type:`` and the plant's own keys) and the problem
keys (`sep_plant.problem.Problem`) beside it, and optionally a ``design:`` section with the
scenario's defaults for the design tool (e.g. ``n_r: 40``; command-line options override them)::

    plant:
      type: slab              # built-in, a `sep.plants` entry point, or "package.module:ClassName"
      n_x: 100
      dt: 0.25
    n_steps: 250
    target: 150.0
    band_window: [150, 250]

A file without a ``plant:`` section means the default plant (the slab of the reference
scenario) with its problem keys: ``u_min: 0.0`` alone is the reference with that limit. Files
in the earlier flat format (every key of the slab and its problem at the top level, as in sep
0.1's ``reference.yaml``) are still read, recognised by a key only that format has (a slab
key such as ``n_x``, or ``t_target``, ``q_late``, ``q_early``, ``k_band``): they mean the slab.
Unknown keys and out-of-range values are refused with a `ScenarioError` that names the key.

`load_scenario` builds the plant once (its constructor checks its keys), checks that the
problem fits it (vector lengths, target), and stores the plant's complete configuration, so
two scenarios that mean the same plant compare equal. Scenarios read from JSON (a design file,
the scenario topic, a bag) are plain data: nothing is imported until `plant` is asked for.

Files. A plant key that names a file (one the plant class lists in its `path_keys`, e.g. the
fmu plant's ``path``) is resolved relative to the scenario file's folder when it is relative.
A plant that reads a file reports it in its configuration by absolute path under a key K and
the file's SHA-256 under ``K_sha256``; scenarios compare such a file by its SHA-256, not its
path (the same FMU in two folders is the same plant, another FMU under the same name is not).
Pure Python/numpy: no ROS import.
"""
from __future__ import annotations

import functools
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from sep_plant.plants import PlantConfigError, PlantTypeError, make_plant, resolve
from sep_plant.problem import Problem, ProblemError, decode_inf
from sep_plant.protocol import PlantInfo, noise_channels

FORMAT = "sep-scenario"
FORMAT_VERSION = 2

#: keys of the sep 0.1 flat scenario format that belong to the slab plant
LEGACY_PLANT_KEYS = ("n_x", "length", "k0", "beta", "gamma", "t_ref", "t_scale", "eta", "t_right", "t_init",
                     "heater_centers", "heater_sigma", "sensor_positions", "dt")
#: flat-format problem keys -> problem keys (k_band is handled separately: [k_band, n_steps])
LEGACY_PROBLEM_KEYS = {"n_steps": "n_steps", "t_target": "target", "band": "band", "q_late": "q_window",
                       "q_early": "q_outside", "r_u": "r_u", "w_std": "w_std", "v_std": "v_std",
                       "u_min": "u_min", "u_max": "u_max", "lqr_k_switch": "lqr_k_switch",
                       "lqr_q_late": "lqr_q_late", "lqr_q_early": "lqr_q_early", "lqr_r": "lqr_r",
                       "u_init": "u_init"}
#: keys that only the flat format has: a file without `plant:` holding one of them is a flat file
LEGACY_ONLY_KEYS = frozenset(LEGACY_PLANT_KEYS) | {k for k, v in LEGACY_PROBLEM_KEYS.items() if k != v} | {"k_band"}
#: the plant of a scenario that names none (the reference scenario's)
DEFAULT_PLANT = "slab"


class ScenarioError(ValueError):
    """A scenario value is missing, unknown or out of range, or its plant cannot be built."""


@dataclass(frozen=True, eq=False)
class Scenario:
    """A plant (type + its own keys) and a problem. Equality and hash follow `to_json`."""

    plant_type: str = DEFAULT_PLANT
    plant_config: Mapping[str, Any] = field(default_factory=dict)
    problem: Problem = field(default_factory=Problem)
    #: the scenario's own defaults for the design tool (`design:` section: DesignSettings keys,
    #: e.g. n_r, belief); checked by the design tool, not part of the plant or the problem
    design: Mapping[str, Any] = field(default_factory=dict)

    # -------------------------------------------------------------- the plant
    @functools.cached_property
    def plant(self):
        """The plant object (built on first use; its constructor checks its keys)."""
        try:
            p = make_plant(self.plant_type, self.plant_config)
        except (PlantTypeError, PlantConfigError) as exc:
            raise ScenarioError(str(exc)) from None
        try:
            self.problem.check_dims(int(p.n_u), int(p.n_y), noise_channels(p), np.asarray(p.field_coordinates()),
                                      float(p.dt))
        except ProblemError as exc:
            raise ScenarioError(f"plant {self.plant_type!r}: {exc}") from None
        return p

    @property
    def info(self) -> PlantInfo:
        return PlantInfo.of(self.plant)

    def canonical(self) -> "Scenario":
        """The same scenario with the plant's complete configuration (builds the plant, which the
        new scenario keeps: its configuration is that plant's)."""
        out = Scenario(self.plant_type, plain_config(self.plant.config()), self.problem.resolved(),
                       dict(self.design))
        out.__dict__["plant"] = self.plant       # the cached_property's slot
        return out

    # ------------------------------------------------------------ variations
    def replace(self, **problem_changes: Any) -> "Scenario":
        """A scenario with some problem keys changed (same plant)."""
        return Scenario(self.plant_type, dict(self.plant_config), self.problem.replace(**problem_changes),
                        dict(self.design))

    def with_plant(self, plant_type: str | None = None, **config_changes: Any) -> "Scenario":
        """A canonical scenario with some plant keys changed (or another plant type)."""
        cfg = {} if plant_type not in (None, self.plant_type) else dict(self.plant_config)
        cfg.update(config_changes)
        return Scenario(plant_type or self.plant_type, cfg, self.problem, dict(self.design)).canonical()

    # ------------------------------------------------------- (de)serialize
    def to_dict(self) -> dict[str, Any]:
        out = {"format": FORMAT, "version": FORMAT_VERSION,
               "plant": {"type": self.plant_type, **dict(self.plant_config)}, **self.problem.to_dict()}
        if self.design:
            out["design"] = dict(self.design)
        return out

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True, default=json_default)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Scenario) and self.to_json() == other.to_json()

    def __hash__(self) -> int:
        return hash(self.to_json())

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "scenario", canonical: bool = True,
                  base_dir: str | Path | None = None) -> "Scenario":
        """Parse a scenario mapping (current or flat sep 0.1 format; no `plant:` and no flat-only
        key: the default plant).

        Parameters
        ----------
        data : the scenario's keys.
        source : what to name in error messages (the file).
        canonical : build the plant to check it and store its complete configuration.
        base_dir : the folder that relative file keys of the plant (its class's `path_keys`)
            are relative to (the scenario file's); None leaves them as they are.

        Returns
        -------
        The scenario; `ScenarioError` naming the key when a value is wrong.
        """
        if not isinstance(data, Mapping):
            raise ScenarioError(f"{source}: expected a mapping of scenario keys, got {type(data).__name__}")
        data = dict(data)
        design = data.pop("design", None) or {}
        if not isinstance(design, Mapping) or not all(isinstance(k, str) for k in design):
            raise ScenarioError(f"{source}: `design:` must be a mapping of design settings (e.g. n_r: 40), "
                                f"got {design!r}")
        if "plant" not in data and LEGACY_ONLY_KEYS.intersection(data):
            scen = _parse_legacy(data, source)
        elif "plant" in data:
            scen = _parse_current(data, source, base_dir)
        else:   # a file of problem keys only (or none) means the default plant
            scen = _parse_current({"plant": {"type": DEFAULT_PLANT}, **data}, source)
        scen = Scenario(scen.plant_type, scen.plant_config, scen.problem, plain_config(design))
        if canonical:
            try:
                return scen.canonical()
            except ScenarioError as exc:
                raise ScenarioError(f"{source}: {exc}") from None
        return scen

    @classmethod
    def from_json(cls, text: str, canonical: bool = False) -> "Scenario":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ScenarioError(f"scenario JSON: {exc}") from None
        return cls.from_dict(data, "scenario JSON", canonical=canonical)

    # -------------------------------------------------------------- compare
    def plant_mismatches(self, other: "Scenario") -> list[str]:
        """Where `other` means another plant or horizon than this scenario (empty when they
        match): the plant type, every plant key, and n_steps. Problem keys (noise, weights,
        limits) may differ: each node uses its own. A file key K that both configurations carry
        with its SHA-256 (``K_sha256``) compares by content: its paths may differ."""
        out = []
        if self.plant_type != other.plant_type:
            return [f"plant type: {self.plant_type!r} != {other.plant_type!r}"]
        a, b = dict(self.plant_config), dict(other.plant_config)
        files = {k for k in set(a) & set(b) if isinstance(k, str) and f"{k}_sha256" in a and f"{k}_sha256" in b}
        for k in sorted(set(a) | set(b), key=str):
            if k in files:
                continue
            if isinstance(k, str) and k.endswith("_sha256") and k[:-7] in files:
                if a[k] != b[k]:
                    out.append(f"plant.{k[:-7]}: another file ({a[k[:-7]]!r}, SHA-256 {str(a[k])[:12]}... != "
                               f"{b[k[:-7]]!r}, SHA-256 {str(b[k])[:12]}...)")
                continue
            if k not in a or k not in b:
                out.append(f"plant.{k}: {'missing' if k not in a else repr(a[k])} != "
                           f"{'missing' if k not in b else repr(b[k])}")
            elif not same_value(a[k], b[k]):
                out.append(f"plant.{k}: {a[k]!r} != {b[k]!r}")
        if self.problem.n_steps != other.problem.n_steps:
            out.append(f"n_steps: {self.problem.n_steps} != {other.problem.n_steps}")
        return out


def mismatches(a: Scenario, b: Scenario) -> list[str]:
    """Human-readable list of plant keys where two scenarios differ (empty when they match)."""
    return a.plant_mismatches(b)


@functools.lru_cache(maxsize=1)
def reference() -> Scenario:
    """The shipped reference scenario (docs/method.md): the slab with every default."""
    return Scenario().canonical()


@functools.lru_cache(maxsize=None)
def _yaml_loader():
    """PyYAML's safe loader, with numbers in exponent form without a dot (1e-6) read as floats:
    YAML 1.1 reads them as strings (YAML 1.2 and JSON as numbers)."""
    import re

    import yaml

    class Loader(yaml.SafeLoader):
        pass

    Loader.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(r"^[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+$"),
                                 list("-+0123456789"))
    return Loader


def load_yaml(text: str) -> Any:
    """A YAML document as scenario files (and KEY=VALUE settings) are read: safe, 1e-6 a number."""
    import yaml  # local import: only file loading needs PyYAML

    return yaml.load(text, Loader=_yaml_loader())


def load_scenario(path: str | Path | None) -> Scenario:
    """Load a YAML scenario file (canonical); None gives the reference scenario.

    Only keys that differ from the defaults need to be present.
    """
    if path is None:
        return reference()
    import yaml  # local import: only file loading needs PyYAML

    p = Path(path)
    if not p.is_file():
        raise ScenarioError(f"scenario file not found: {p}")
    try:
        data = load_yaml(p.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{p}: not a YAML scenario file: {exc}") from None
    except OSError as exc:
        raise ScenarioError(f"{p}: cannot read: {exc}") from None
    if data is None:
        data = {}
    if isinstance(data, Mapping) and "scenario" in data and len(data) == 1:
        data = data["scenario"]
    return Scenario.from_dict(data, str(p), base_dir=p.absolute().parent)


# ---------------------------------------------------------------- internals
def _resolve_paths(plant_type: str, plant: dict, base_dir: str | Path | None) -> dict:
    """`plant` with the relative file keys its class declares (`path_keys`) made absolute
    against `base_dir` (an unknown type is left for the plant's construction to report)."""
    if base_dir is None:
        return plant
    try:
        cls = resolve(plant_type)
    except PlantTypeError:
        return plant
    for key in getattr(cls, "path_keys", ()):
        value = plant.get(key)
        if isinstance(value, str) and value:
            value = os.path.expanduser(value)
            plant[key] = value if os.path.isabs(value) else os.path.abspath(os.path.join(str(base_dir), value))
    return plant


def _parse_current(data: dict, source: str, base_dir: str | Path | None = None) -> Scenario:
    plant = data.pop("plant")
    data.pop("format", None)
    version = data.pop("version", FORMAT_VERSION)
    if version != FORMAT_VERSION:
        raise ScenarioError(f"{source}: scenario format version {version!r}, this sep reads {FORMAT_VERSION}")
    if not isinstance(plant, Mapping):
        raise ScenarioError(f"{source}: `plant:` must be a mapping with `type:` and the plant's keys, got {plant!r}")
    plant = dict(plant)
    ptype = plant.pop("type", None)
    if not isinstance(ptype, str) or not ptype.strip():
        raise ScenarioError(f"{source}: `plant:` needs `type:` (e.g. slab, or 'package.module:ClassName')")
    try:
        problem = Problem.from_dict(data, source)
    except ProblemError as exc:
        raise ScenarioError(str(exc)) from None
    plant = _resolve_paths(ptype.strip(), plant, base_dir)
    return Scenario(ptype.strip(), plain_config(plant), problem)


def _parse_legacy(data: dict, source: str) -> Scenario:
    known = set(LEGACY_PLANT_KEYS) | set(LEGACY_PROBLEM_KEYS) | {"k_band"}
    unknown = sorted((str(k) for k in data if k not in known))
    if unknown:
        flat_only = sorted(str(k) for k in LEGACY_ONLY_KEYS.intersection(data))
        if any(k in Problem.__dataclass_fields__ for k in unknown):   # current keys beside flat ones
            raise ScenarioError(f"{source}: unknown key(s) {unknown} for sep 0.1's flat slab format, which "
                                f"the key(s) {flat_only} select; in the current format the plant keys go under "
                                f"`plant:` (e.g. plant: {{type: slab, {flat_only[0]}: ...}}) beside the problem "
                                f"keys {sorted(Problem.__dataclass_fields__)}")
        raise ScenarioError(f"{source}: unknown key(s) {unknown}; a scenario has a `plant:` section "
                            f"(type and plant keys) and the problem keys {sorted(Problem.__dataclass_fields__)}; "
                            f"the flat slab format knows {sorted(known)}")
    plant = {k: decode_inf(data[k]) for k in LEGACY_PLANT_KEYS if k in data}
    prob = {LEGACY_PROBLEM_KEYS[k]: data[k] for k in LEGACY_PROBLEM_KEYS if k in data}
    # the flat format's semantics: band from k_band (default 150) to N, LQR switch default 120
    prob["band_window"] = [data.get("k_band", 150), prob.get("n_steps", Problem().n_steps)]
    prob.setdefault("lqr_k_switch", 120)
    try:
        problem = Problem.from_dict(prob, source)
    except ProblemError as exc:
        raise ScenarioError(str(exc)) from None
    return Scenario("slab", plain_config(plant), problem)


def plain_config(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """YAML/JSON data as plain JSON types (numpy values -> numbers and lists, tuples -> lists),
    keys as given: what a scenario stores of a plant's configuration."""
    return json.loads(json.dumps(dict(cfg), default=json_default))


def json_default(v: Any) -> Any:
    """`json.dumps(..., default=json_default)`: numpy scalars and arrays as plain numbers and lists
    (the one converter of sep's JSON outputs: scenarios, design files, summaries, metrics)."""
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    raise TypeError(f"not JSON serializable: {type(v).__name__}")


def same_value(a: Any, b: Any) -> bool:
    """Equal scenario values: numbers to 1e-12 (a float round trip is not a difference), lists
    and mappings element by element, anything else by ==."""
    if isinstance(a, bool) or isinstance(b, bool):
        return a == b
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return math.isclose(float(a), float(b), rel_tol=1e-12, abs_tol=1e-12)
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(same_value(x, y) for x, y in zip(a, b))
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return set(a) == set(b) and all(same_value(a[k], b[k]) for k in a)
    return a == b


# ------------------------------------------------------------- scenario topic
def scenario_payload(scenario: Scenario, info: PlantInfo, perturbation: Mapping[str, Any] | None = None,
                     episode: Mapping[str, int] | None = None) -> str:
    """The JSON the plant publishes on the scenario topic (and bags keep): the scenario and the
    plant's description, so that nodes, the recorder and the analysis need not import the plant;
    with a perturbation of its actuators and sensors (`sep_plant.perturb`: the non-neutral values
    per key) also ``"perturbation"``, so that controllers and bag analyses see the plant they ran on;
    for a plant that plays several episodes (parameter ``episodes`` != 1) also ``"episode"``
    (`episode_entry`), published anew before each episode."""
    data: dict[str, Any] = {"scenario": scenario.to_dict(), "plant_info": info.to_dict()}
    if perturbation:
        data["perturbation"] = {str(k): v for k, v in perturbation.items()}
    if episode is not None:
        data["episode"] = {str(k): int(v) for k, v in episode.items()}
    return json.dumps(data, sort_keys=True, default=json_default)


def episode_entry(index: int, episodes: int, seed: int, run: int) -> dict[str, int]:
    """The ``"episode"`` entry of the scenario message of episode `index` (0-based) of a plant that
    plays `episodes` episodes (0: until stopped); it plays Monte Carlo run `run` of `seed`."""
    return {"index": int(index), "of": int(episodes), "seed": int(seed), "run": int(run)}


def parse_scenario_message(text: str) -> tuple[Scenario, PlantInfo, dict[str, list[float]]]:
    """(scenario, plant description, perturbation) of one scenario-topic message, parsed once:
    `parse_scenario_payload` and the perturbation the plant node publishes ({} for an
    unperturbed plant and for messages that carry none); ScenarioError naming what is wrong."""
    return scenario_message_parts(text)[:3]


def scenario_message_parts(text: str) -> tuple[Scenario, PlantInfo, dict[str, list[float]], dict[str, int] | None]:
    """`parse_scenario_message` and the message's ``"episode"`` entry (None: a single-episode plant)."""
    data = _message_json(text)
    return (*_scenario_of(data), _perturbation_of(data), _episode_of(data))


def _episode_of(data: Any) -> dict[str, int] | None:
    ep = data.get("episode") if isinstance(data, Mapping) else None
    if ep is None:
        return None
    try:
        out = {k: int(ep[k]) for k in ("index", "of", "seed", "run")}
    except (TypeError, KeyError, ValueError):
        raise ScenarioError(f"scenario message: episode must map index, of, seed, run to integers, got {ep!r}") from None
    if out["index"] < 0 or out["of"] < 0 or (out["of"] and out["index"] >= out["of"]):
        raise ScenarioError(f"scenario message: bad episode entry {ep!r}")
    return out


def parse_scenario_payload(text: str) -> tuple[Scenario, PlantInfo]:
    """(scenario, plant description) of a scenario-topic message. sep 0.1 published the flat slab
    scenario alone: its description comes from the built-in slab."""
    return _scenario_of(_message_json(text))


def _message_json(text: str) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ScenarioError(f"scenario message: {exc}") from None


def _perturbation_of(data: Any) -> dict[str, list[float]]:
    pert = data.get("perturbation", {}) if isinstance(data, Mapping) else {}
    if not isinstance(pert, Mapping):
        raise ScenarioError(f"scenario message: perturbation must be a mapping, got {pert!r}")
    out = {}
    for key, value in pert.items():
        try:
            arr = np.asarray(value, dtype=float) if not isinstance(value, (str, bytes, Mapping)) else None
        except (TypeError, ValueError):
            arr = None
        if arr is None or arr.ndim > 1:
            raise ScenarioError(f"scenario message: perturbation {key}: expected a number or a list of numbers, "
                                f"got {value!r}")
        out[str(key)] = np.atleast_1d(arr).tolist()
    return out


def _scenario_of(data: Any) -> tuple[Scenario, PlantInfo]:
    if isinstance(data, Mapping) and "scenario" in data and "plant_info" in data:
        scen = Scenario.from_dict(data["scenario"], "scenario message", canonical=False)
        try:
            return scen, PlantInfo.from_dict(data["plant_info"])
        except (TypeError, ValueError, KeyError) as exc:
            raise ScenarioError(f"scenario message: bad plant_info: {exc}") from None
    scen = Scenario.from_dict(data, "scenario message (sep 0.1 format)")
    return scen, scen.info
