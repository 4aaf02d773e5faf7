"""The source record of a design: everything a design was made from, and its SHA-256 digest.

A design is a function of its plant (type and complete keys, its code, and the contents of any
file the plant reads), its resolved problem, the design settings that change the result, the
code of sep that made it and the design-file format. The record lists exactly these, as plain
JSON data::

    {"format_version": 4,
     "sep_version": "0.9.0",                                # the sep that made the design
     "plant": {"type": "slab", "n_x": 100, ...},           # complete configuration
     "plant_code": {"builtin": true},                       # or, for a plant outside sep:
     #   {"module": "my_pkg.plant", "package": "my_pkg", "package_version": "1.2.0",
     #    "module_sha256": "<sha256 of the module's source file>"}
     "plant_files": {"model.fmu": "<sha256 of its bytes>"},  # plant.source_files(), if any
     "problem": {"n_steps": 250, "target": 150.0, ...},     # resolved (band_window, lqr_k_switch)
     "settings": {"n_r": 20, "chunks": 4, ..., "jacobian_used": "sensitivity"}}

The plant's code (`plant_code`): a built-in plant is sep's own code, identified by
``sep_version``; a plant from another package (an entry point or a ``module:Class`` import
path) by its module, the version of the distribution that installs its top-level package (None
for a module on PYTHONPATH) and the SHA-256 of the module's source file (the module that
defines the class: a change to a module it imports is seen only through the package version).
So a design made by another sep, another version of a plant package or an edited plant module
is a different design (`sep demo` redesigns); the design's arrays do not depend on the record.

and its digest is the SHA-256 of its canonical JSON (sorted keys, no spaces). A plant key K
that names a file whose SHA-256 the configuration carries (``K_sha256``, e.g. the fmu plant's
``path``) is recorded by that digest only, not by its path: the same FMU in another folder is
the same input, as scenarios compare it (`sep_plant.scenario`). Two designs with
the same digest were made from the same inputs; a tool that would reuse a design file (`sep
demo`) compares digests (`source_differences`), and `record_differences` names what differs
when they do not match. `design_source` is the record of a `Design`.

Settings that change how the work is spread but not the numbers beyond round-off are left out
(`RESULT_NEUTRAL_SETTINGS`): the memory budget only splits batches of independent runs. It can
also switch the 'auto' Jacobian to the ROM one when the sensitivity batch would not fit, so the
record carries the Jacobian the design used (``jacobian_used``) instead. Threads, Dask and the
device are not settings at all (same results to round-off, see docs/reference/cli.md).
Pure Python: no ROS import.
"""
from __future__ import annotations

import functools
import hashlib
import importlib
import json
from pathlib import Path
from typing import Any, Mapping

from sep_plant.plants import PlantTypeError, resolve
from sep_plant.scenario import Scenario, json_default

from sep_estimator.design import Design

#: design settings left out of the record: they change the batching, not the design
RESULT_NEUTRAL_SETTINGS = ("memory_budget",)
#: the record's settings key of the Jacobian the design used ('auto' resolved)
JACOBIAN_USED = "jacobian_used"

_MISSING = object()


def file_digest(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes, read in 1 MiB blocks; 'unreadable: <reason>' if it cannot
    be read (a difference, never an exception: the caller decides what a missing file means)."""
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    except OSError as exc:
        return f"unreadable: {exc.strerror or exc}"
    return h.hexdigest()


def plant_file_digests(plant: Any) -> dict[str, str]:
    """{name: SHA-256} of the files the plant reads, from its optional method
    ``source_files() -> dict[str, path]`` (e.g. an FMU); {} for plants without files."""
    files = getattr(plant, "source_files", None)
    if files is None:
        return {}
    return {str(name): file_digest(path) for name, path in sorted(dict(files()).items(), key=lambda kv: str(kv[0]))}


def plant_code(plant_type: str) -> dict[str, Any] | None:
    """The identity of the plant class's code (see the module docstring): {"builtin": True} for
    sep's own plants, else its module, package, package version and module SHA-256; None when
    the plant type cannot be resolved here."""
    from sep_plant.plants import BUILTIN

    if plant_type.strip() in BUILTIN:
        return {"builtin": True}
    try:
        cls = resolve(plant_type)
    except PlantTypeError:
        return None
    name = getattr(cls, "__module__", None) or ""
    try:
        source = getattr(importlib.import_module(name), "__file__", None) if name else None
    except ImportError:
        source = None
    top = name.split(".")[0]
    return {"module": name, "package": top, "package_version": _distribution_version(top),
            "module_sha256": file_digest(source) if source else None}


@functools.lru_cache(maxsize=64)
def _distribution_version(top_level: str) -> str | None:
    """The version of the installed distribution that provides package `top_level` (None: none
    does, e.g. a module on PYTHONPATH)."""
    from importlib.metadata import PackageNotFoundError, packages_distributions, version

    for dist in sorted(packages_distributions().get(top_level, [])):
        try:
            return version(dist)
        except PackageNotFoundError:
            continue
    return None


def _sep_version() -> str:
    import sep_plant

    return str(sep_plant.__version__)


def source_record(plant_type: str, plant_config: Mapping[str, Any], plant_files: Mapping[str, str],
                  problem: Mapping[str, Any], settings: Mapping[str, Any], format_version: int,
                  code: Mapping[str, Any] | None = None, sep_version: str | None = None) -> dict[str, Any]:
    """The source record (see the module docstring) as plain JSON data.

    Parameters
    ----------
    plant_type, plant_config : str, mapping
        The plant's type string and its complete configuration (``plant.config()``; file keys
        that come with their SHA-256 are left out, the digest stays).
    plant_files : mapping
        {name: SHA-256} of the files the plant reads (`plant_file_digests`).
    problem : mapping
        The resolved problem as ``Problem.to_dict()`` writes it.
    settings : mapping
        The design settings (``dataclasses.asdict(DesignSettings)``) with ``jacobian_used``;
        the `RESULT_NEUTRAL_SETTINGS` are dropped.
    format_version : int
        The design-file format version.
    code : mapping, optional
        The plant's code identity (`plant_code`); None: recorded as null (type not resolvable).
    sep_version : str, optional
        The version of sep (default: this one's).

    Returns
    -------
    dict
        The record, normalized through JSON (tuples as lists, numpy values as numbers).
    """
    config = {k: v for k, v in plant_config.items() if not (isinstance(k, str) and f"{k}_sha256" in plant_config)}
    record = {"format_version": int(format_version), "sep_version": sep_version or _sep_version(),
              "plant": {"type": plant_type, **config}, "plant_code": None if code is None else dict(code),
              "plant_files": dict(plant_files), "problem": dict(problem),
              "settings": {k: v for k, v in settings.items() if k not in RESULT_NEUTRAL_SETTINGS}}
    return json.loads(json.dumps(record, default=json_default))


def source_digest(record: Mapping[str, Any]) -> str:
    """SHA-256 (hex) of the record's canonical JSON (sorted keys, compact separators)."""
    text = json.dumps(record, sort_keys=True, separators=(",", ":"), default=json_default)
    return hashlib.sha256(text.encode()).hexdigest()


def record_differences(recorded: Any, expected: Any, path: tuple[str, ...] = ()) -> list[str]:
    """Every value where two source records differ, recorded first: "problem.target: 150.0 !=
    151.0", "settings.n_r: 20 != 40", "plant file model.fmu: sha256 1f2e3d4c5b6a != ...".
    Values compare exactly (type included: 1 and 1.0 have different digests)."""
    if isinstance(recorded, Mapping) and isinstance(expected, Mapping):
        out: list[str] = []
        for key in sorted(set(recorded) | set(expected), key=str):
            out += record_differences(recorded.get(key, _MISSING), expected.get(key, _MISSING), path + (str(key),))
        return out
    if type(recorded) is type(expected) and recorded == expected:
        return []
    if path[:1] == ("plant_files",) and len(path) == 2:
        return [f"plant file {path[1]}: sha256 {_short(recorded)} != {_short(expected)}"]
    label = {("format_version",): "design-file format version", ("sep_version",): "sep version",
             ("plant_code", "module_sha256"): "plant module source sha256"}.get(path, ".".join(path))
    if path == ("plant_code", "module_sha256"):
        return [f"{label}: {_short(recorded)} != {_short(expected)}"]
    return [f"{label}: {_show(recorded)} != {_show(expected)}"]


def _show(v: Any) -> str:
    return "missing" if v is _MISSING else repr(v)


def _short(v: Any) -> str:
    return "missing" if v is _MISSING else (v[:12] if isinstance(v, str) and len(v) == 64 else str(v))


# ------------------------------------------------------------------ the record of a design
def design_source(d: Design) -> dict[str, Any]:
    """The source record of a design: its scenario's plant and resolved problem, the digests of
    the plant's files and the identity of its code, its settings (``meta["settings"]``) with the
    Jacobian it used (``meta["optimizer"]["jacobian"]``), this sep's version, and the version of
    the design-file format that writes it (`sep_estimator.design_file.VERSION`)."""
    settings = dict(d.meta.get("settings", {}))
    used = d.meta.get("optimizer", {}).get("jacobian")
    if used is not None:
        settings[JACOBIAN_USED] = used
    files, code = _plant_files(d.scenario), plant_code(d.scenario.plant_type)
    if files is None:       # the plant's code is not importable here: keep what was recorded
        files = d.meta.get("source", {}).get("plant_files", {})
    if code is None:
        code = d.meta.get("source", {}).get("plant_code")
    return source_record(d.scenario.plant_type, d.scenario.plant_config, files, d.problem.resolved().to_dict(),
                         settings, _format_version(), code)


def source_differences(design: Design, scenario: Scenario, settings: Mapping[str, Any]) -> list[str]:
    """What differs between the inputs a design file was made from and `scenario` + `settings`.

    Parameters
    ----------
    design : Design
        A loaded design (its ``meta["source"]`` and ``meta["source_digest"]``).
    scenario : Scenario
        The scenario to design for now (canonical: complete plant keys).
    settings : mapping
        The design settings as a design would record them: ``dataclasses.asdict(settings)``
        with ``jacobian_used``, the Jacobian 'auto' resolves to for this plant
        (`sep_control.cli.design.recorded_settings`).

    Returns
    -------
    list of str
        Empty when the digest of the expected record equals the file's; else one line per
        difference, e.g. "problem.target: 150.0 != 151.0" (the file's value first).
    """
    recorded, digest = design.meta.get("source"), design.meta.get("source_digest")
    if not isinstance(recorded, Mapping) or not isinstance(digest, str):
        return ["the design file has no source record (written by a sep that did not record its inputs)"]
    if source_digest(recorded) != digest:
        return ["the design file's source record does not match its digest (its metadata was edited)"]
    files = _plant_files(scenario)
    expected = source_record(scenario.plant_type, scenario.plant_config, {} if files is None else files,
                             scenario.problem.resolved().to_dict(), settings, _format_version(),
                             plant_code(scenario.plant_type))
    if source_digest(expected) == digest:
        return []
    return record_differences(recorded, expected) or [f"source digest {digest[:12]} != {source_digest(expected)[:12]}"]


def _format_version() -> int:
    """The version of the design-file format (`sep_estimator.design_file.VERSION`)."""
    from sep_estimator.design_file import VERSION   # imported here: design_file imports this module

    return VERSION


def _plant_files(scenario: Scenario) -> dict[str, str] | None:
    """Digests of the scenario's plant files ({} for plant classes without `source_files`, None
    when the plant type cannot be resolved here); builds the plant only when it has files."""
    try:
        cls = resolve(scenario.plant_type)
    except PlantTypeError:
        return None
    return plant_file_digests(scenario.plant) if hasattr(cls, "source_files") else {}

