"""What sep needs from an FMU's modelDescription.xml, checked: interface, states, variables.

`describe(path)` reads the model description (fmpy) and `Description` answers the plant's
questions with value references: which interface to use, the continuous states (Model
Exchange), the variables named by the scenario's keys, and every reason the FMU cannot serve
as a sep plant. Problems are collected as sentences (the plant raises them all at once, naming
the FMU), never raised one by one.

Variable selections. A scenario names variables by their FMU names. A selection is a list of
elements (value reference, element index) in order: a scalar variable is one element, an FMI 3.0
array variable (``T`` with dimensions) is its elements in C order, and an FMI 2.0 array written
in the structured naming convention (``T[1]`` .. ``T[n]``, ``T[1,1]`` .. ``T[n,m]``) is found
by its base name ``T``: the elements sorted by their indices, which must fill a full box
(1..n per axis). Its shape is the box's (`Selection.shape`), the field's default grid_shape.
Pure Python: no ROS import (fmpy is imported when an FMU is read).
"""
from __future__ import annotations

import itertools
import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

#: FMI variable types that carry a float64 value (FMI 2.0 Real, FMI 3.0 Float64)
REAL_TYPES = ("Real", "Float64")
INTEGER_TYPES = ("Integer", "Enumeration", "Int8", "UInt8", "Int16", "UInt16", "Int32", "UInt32", "Int64",
                 "UInt64")
INTERFACES = ("model_exchange", "co_simulation")


@dataclass(frozen=True)
class Selection:
    """Variables picked by name: their value references and (FMI 3.0 arrays) element counts."""

    names: tuple[str, ...]                   # one per element (e.g. T[1], T[2] or T[0], T[1] for arrays)
    refs: tuple[int, ...]                    # value references of the variables, in order
    sizes: tuple[int, ...]                   # elements per variable (1 for scalars)
    shape: tuple[int, ...] | None = None     # a single array's shape (the default grid_shape)
    elements: tuple[tuple[int, int], ...] = field(default=())   # (value reference, element index)

    @property
    def n(self) -> int:
        return len(self.elements)


def _major(version: str | None) -> int | None:
    try:
        return int(str(version).split(".")[0])
    except (TypeError, ValueError):
        return None


def platform_binary(version: int, model_identifier: str) -> str:
    """The archive member of this machine's shared library for FMI `version`."""
    import fmpy

    folder = fmpy.platform if version == 2 else fmpy.platform_tuple
    return f"binaries/{folder}/{model_identifier}{fmpy.sharedLibraryExtension}"


class Description:
    """A model description and the problems found in it (see the module docstring)."""

    def __init__(self, md: Any, members: set[str], single_set: frozenset[str] = frozenset()):
        self.md = md
        self.single_set = single_set     # variables with canHandleMultipleSetPerTimeInstant = false
        self.version = _major(md.fmiVersion)
        self.problems: list[str] = []
        self.by_name = {v.name: v for v in md.modelVariables}
        self._members = members

    # ------------------------------------------------------------------ interface
    def interfaces(self) -> tuple[str, ...]:
        return tuple(i for i, attr in zip(INTERFACES, ("modelExchange", "coSimulation"))
                     if getattr(self.md, attr, None) is not None)

    def choose_interface(self, wanted: str) -> str | None:
        """The interface to use ("auto": Model Exchange when there is one, its states being real
        numbers the belief and the oracle can work with), with problems noted."""
        have = self.interfaces()
        if not have:
            self.problems.append("it provides neither Model Exchange nor Co-Simulation")
            return None
        if wanted == "auto":
            return have[0]
        if wanted not in have:
            self.problems.append(f"interface {wanted} is not provided (the FMU has {', '.join(have)})")
            return None
        return wanted

    def check_interface(self, interface: str) -> None:
        """Problems of `interface` for sep: version, platform binary, events, FMU state."""
        if self.version not in (2, 3):
            self.problems.append(f"FMI version {self.md.fmiVersion!r} is not supported (sep reads FMI 2.0 and 3.0)")
            return
        attrs = self.md.modelExchange if interface == "model_exchange" else self.md.coSimulation
        member = platform_binary(self.version, attrs.modelIdentifier)
        if member not in self._members:
            have = sorted({m.split("/")[1] for m in self._members if m.startswith("binaries/") and m.count("/") >= 2})
            self.problems.append(f"no binary for this platform ({member} is missing; the FMU has binaries for "
                                 f"{', '.join(have) or 'no platform'})")
        if getattr(attrs, "canBeInstantiatedOnlyOncePerProcess", False):
            self.problems.append("it can be instantiated only once per process (canBeInstantiatedOnlyOncePerProcess): "
                                 "sep builds several instances (checks, rebuilt plants)")
        if interface == "model_exchange":
            if self.md.numberOfEventIndicators:
                self.problems.append(
                    f"the Model Exchange FMU has {self.md.numberOfEventIndicators} event indicator(s): sep "
                    "integrates it with a fixed-step RK4 that does not locate state events; use its "
                    "Co-Simulation interface (interface: co_simulation) or export it without events")
            if not self.md.numberOfContinuousStates:
                self.problems.append("the Model Exchange FMU has no continuous states (nothing for sep to integrate)")
        else:
            if not attrs.canGetAndSetFMUstate:
                self.problems.append("the Co-Simulation FMU cannot get and set its FMU state (canGetAndSetFMUstate): "
                                     "sep restarts experiments from copied states")
            if not attrs.canSerializeFMUstate:
                self.problems.append("the Co-Simulation FMU cannot serialize its FMU state (canSerializeFMUstate): "
                                     "sep keeps states as rows of numbers")

    # ------------------------------------------------------------------ variables
    def state_selection(self) -> Selection:
        """The continuous states in the order of the state vector (Model Exchange)."""
        states = []
        for unknown in self.md.derivatives:
            der = unknown.variable
            if der.derivative is None:
                self.problems.append(f"derivative {der.name} names no state variable")
                continue
            states.append(der.derivative)
        return self._selection([s.name for s in states], states)

    def select(self, key: str, names: str | Sequence[str], *, real: bool = True, scalar: bool = False,
               causality: tuple[str, ...] | None = None) -> Selection | None:
        """The variables of a key: a list of names, or (a string) one variable or array."""
        if isinstance(names, str):
            var = self.by_name.get(names)
            found = [var] if var is not None else self._array_elements(names)
            if not found:
                self.problems.append(f"{key}: the FMU has no variable {names!r} (nor array elements "
                                     f"{names}[1], ...){self._hint(names)}")
                return None
            label = [names] if var is not None else [v.name for v in found]
        else:
            missing = [n for n in names if n not in self.by_name]
            for n in missing:
                self.problems.append(f"{key}: the FMU has no variable {n!r}{self._hint(n)}")
            if missing:
                return None
            found, label = [self.by_name[n] for n in names], list(names)
        ok = True
        for v in found:
            if real and v.type not in REAL_TYPES:
                self.problems.append(f"{key}: {v.name} is of type {v.type}, sep needs Real (FMI 2.0) / Float64 "
                                     "(FMI 3.0) variables")
                ok = False
            if causality is not None and v.causality not in causality:
                self.problems.append(f"{key}: {v.name} has causality {v.causality!r}, expected "
                                     f"{' or '.join(causality)}")
                ok = False
            if scalar and _size(v) != 1:
                self.problems.append(f"{key}: {v.name} is an array variable, expected a scalar")
                ok = False
        if not ok:
            return None
        sel = self._selection(label, found)
        if isinstance(names, str) and self.by_name.get(names) is None:
            sel = Selection(sel.names, sel.refs, sel.sizes, self._array_shape(names), sel.elements)
        return sel

    def _selection(self, label: list[str], found: list[Any]) -> Selection:
        names, elements = [], []
        for lab, v in zip(label, found):
            size = _size(v)
            names += [lab] if size == 1 else [f"{lab}[{k}]" for k in range(size)]
            elements += [(v.valueReference, k) for k in range(size)]
        shape = tuple(found[0].shape) if len(found) == 1 and found[0].shape and len(found[0].shape) > 1 else None
        return Selection(tuple(names), tuple(v.valueReference for v in found), tuple(_size(v) for v in found),
                         shape, tuple(elements))

    def _indexed(self, base: str) -> list[tuple[tuple[int, ...], Any]]:
        """(indices, variable) of the elements base[i], base[i,j], ... sorted in C order."""
        pat = re.compile(rf"^{re.escape(base)}\[(\d+(?:,\s*\d+)*)\]$")
        hits = [(tuple(int(i) for i in m.group(1).split(",")), v)
                for v, m in ((v, pat.match(v.name)) for v in self.md.modelVariables) if m]
        return sorted(hits, key=lambda h: h[0])

    def _array_elements(self, base: str) -> list[Any]:
        return [v for _, v in self._indexed(base)]

    def _array_shape(self, base: str) -> tuple[int, ...] | None:
        """The box of an FMI 2.0 structured array's indices (None for one axis); a problem when
        they leave gaps."""
        idx = [i for i, _ in self._indexed(base)]
        dims = {len(i) for i in idx}
        if len(dims) != 1:
            self.problems.append(f"array {base}: its elements mix {sorted(dims)} indices")
            return None
        shape = tuple(max(i[a] for i in idx) for a in range(dims.pop()))
        full = list(itertools.product(*[range(1, s + 1) for s in shape]))
        if idx != full:
            self.problems.append(f"array {base}: its elements do not fill 1..{list(shape)} (found {len(idx)} of "
                                 f"{len(full)})")
            return None
        return shape if len(shape) > 1 else None

    def _hint(self, name: str) -> str:
        import difflib

        close = difflib.get_close_matches(name, list(self.by_name), n=3)
        return f" (did you mean {', '.join(close)}?)" if close else ""

    def default_inputs(self, exclude: Sequence[str] = ()) -> list[str]:
        return [v.name for v in self.md.modelVariables if v.causality == "input" and v.type in REAL_TYPES
                and _size(v) == 1 and v.name not in exclude]

    def default_outputs(self) -> list[str]:
        return [v.name for v in self.md.modelVariables if v.causality == "output" and v.type in REAL_TYPES
                and _size(v) == 1]

    def check_multiple_set(self, inputs: Selection) -> None:
        """Model Exchange: sep sets every input once per run and RK4 stage at one time instant."""
        for name in inputs.names:
            if name in self.single_set:
                self.problems.append(f"input {name} cannot be set several times per time instant "
                                     "(canHandleMultipleSetPerTimeInstant = false): sep sets it for every run "
                                     "and RK4 stage; use the Co-Simulation interface")

    def check_feedthrough(self, outputs: Selection, inputs: Sequence[int]) -> None:
        """Refuse outputs that the model structure declares to depend directly on a driven input:
        sep's outputs are y = h(x)."""
        driven = set(inputs)
        for unknown in self.md.outputs:
            var = unknown.variable
            if var.valueReference not in outputs.refs or unknown.dependencies is None:
                continue
            direct = [d.name for d in unknown.dependencies if d.valueReference in driven and d.causality == "input"]
            if direct:
                self.problems.append(f"output {var.name} depends directly on input(s) {', '.join(direct)} "
                                     "(direct feedthrough): sep's outputs must be functions of the state, "
                                     "y = h(x)")

    def check_start_values(self, values: dict[str, Any]) -> list[tuple[Any, Any]]:
        """(variable, value) pairs of the start_values key, each checked to be settable."""
        out = []
        for name, value in values.items():
            v = self.by_name.get(name)
            if v is None:
                self.problems.append(f"start_values: the FMU has no variable {name!r}{self._hint(name)}")
                continue
            if v.variability == "constant" or v.causality in ("calculatedParameter", "independent") \
                    or (v.initial == "calculated" and v.causality != "input"):
                self.problems.append(f"start_values: {name} cannot be set (causality {v.causality}, variability "
                                     f"{v.variability}, initial {v.initial}); set the parameters it is computed from")
                continue
            if _size(v) != 1:
                self.problems.append(f"start_values: {name} is an array variable; set its elements by name")
                continue
            problem = _value_problem(v, value)
            if problem:
                self.problems.append(f"start_values: {name}: {problem}")
                continue
            out.append((v, value))
        return out

    def default_experiment(self, attr: str) -> float | None:
        de = self.md.defaultExperiment
        value = getattr(de, attr, None) if de is not None else None
        return None if value is None else float(value)

    def unit_of(self, var: Any) -> str:
        unit = var.unit or (var.declaredType.unit if var.declaredType is not None else None)
        return str(unit) if unit else ""


def _size(v: Any) -> int:
    shape = getattr(v, "shape", None)
    if not shape:
        return 1
    n = 1
    for s in shape:
        n *= int(s)
    return n


def _value_problem(v: Any, value: Any) -> str | None:
    """Why `value` does not fit variable `v` (None when it does)."""
    if v.type in REAL_TYPES or v.type == "Float32":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"a {v.type} variable needs a number, got {value!r}"
        if value != value or value in (float("inf"), float("-inf")):
            return f"must be finite, got {value!r}"
    elif v.type in INTEGER_TYPES:
        if isinstance(value, bool) or not (isinstance(value, int) or (isinstance(value, float) and value.is_integer())):
            return f"an {v.type} variable needs an integer, got {value!r}"
    elif v.type == "Boolean":
        if not isinstance(value, bool):
            return f"a Boolean variable needs true or false, got {value!r}"
    elif v.type == "String":
        if not isinstance(value, str):
            return f"a String variable needs a string, got {value!r}"
    else:
        return f"variables of type {v.type} cannot be set by sep"
    return None


def _sniff(path: Path) -> tuple[str | None, frozenset[str]]:
    """The fmiVersion attribute of the root element and the variables that declare
    canHandleMultipleSetPerTimeInstant = false (which fmpy does not read); (None, {}) when the
    XML does not parse (fmpy then says why)."""
    import xml.etree.ElementTree as ET

    version, single = None, set()
    try:
        with zipfile.ZipFile(path) as zf, zf.open("modelDescription.xml") as fh:
            for _, elem in ET.iterparse(fh, events=("start",)):
                if version is None:
                    version = elem.get("fmiVersion") or ""
                if elem.get("canHandleMultipleSetPerTimeInstant") in ("false", "0") and elem.get("name"):
                    single.add(elem.get("name"))
    except (ET.ParseError, KeyError, OSError, zipfile.BadZipFile):
        return version or None, frozenset()
    return version or None, frozenset(single)


def describe(path: Path) -> Description:
    """Read and check the model description of the FMU at `path` (a readable zip archive).

    Raises
    ------
    ValueError naming the problem when the XML cannot be read or does not validate.
    """
    from fmpy import read_model_description

    version, single_set = _sniff(path)
    if version is not None and _major(version) not in (2, 3):
        raise ValueError(f"FMI version {version!r} is not supported (sep reads FMI 2.0 and 3.0)")
    try:
        md = read_model_description(str(path), validate=True)
    except Exception as exc:  # noqa: BLE001 - lxml syntax errors, fmpy ValidationError, KeyError ...
        text = str(exc).strip().replace("\n", " ")
        raise ValueError(f"modelDescription.xml cannot be read: {type(exc).__name__}: {text}") from None
    with zipfile.ZipFile(path) as zf:
        members = set(zf.namelist())
    return Description(md, members, single_set)


__all__ = ["Description", "INTERFACES", "REAL_TYPES", "Selection", "describe", "platform_binary"]
