#!/usr/bin/env python3
"""Build the example rod FMU from its C source: compile, write modelDescription.xml, zip.

    python examples/fmu_rod/build_fmu.py --out examples/fmu_rod/rod.fmu            # ME + CS, 50 nodes
    python examples/fmu_rod/build_fmu.py --out rod_cs.fmu --interface co_simulation --nodes 80

The physics is in src/rod_model.h (a nonlinear thermal rod with K(T), three heaters, three
sensors); src/rod_fmi2.c is its FMI 2.0 interface, src/rod_fmi3.c its FMI 3.0 interface. The
C compiler is $CC, else cc or gcc; the FMI headers are the ones fmpy ships (fmpy/c-code). The
archive is reproducible: fixed timestamps, so the same compiler gives the same SHA-256.

`build_fmu(...)` is also what the tests call (with variants: event indicators declared, no FMU
state, FMI 3.0). Needs only the Python standard library and fmpy (for its headers).
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import uuid
import zipfile
from pathlib import Path
from xml.sax.saxutils import escape

HERE = Path(__file__).resolve().parent
SRC = HERE / "src"
MODEL_IDENTIFIER = "rod"
N_HEATERS = 3
N_SENSORS = 3

#: the Real parameters in value-reference order (name, start, unit, description); the C
#: defaults in src/rod_model.h (rod_defaults) are the same numbers
PARAMETERS = [
    ("length", 1.0, "m", "rod length L"),
    ("k0", 0.002, "m2/s", "conductivity (diffusivity) at t_ref"),
    ("beta", 0.5, "1", "K(T) = k0 (1 + beta (T - t_ref) / t_scale)"),
    ("t_ref", 100.0, "F", "reference temperature of K(T)"),
    ("t_scale", 50.0, "F", "temperature scale of K(T)"),
    ("eta", 0.002, "1/s", "cooling rate towards t_amb"),
    ("t_amb", 70.0, "F", "ambient temperature"),
    ("t_right", 150.0, "F", "temperature held at x = L"),
    ("t_init", 100.0, "F", "initial temperature of every node"),
    ("heater_sigma", 0.05, "1", "heater width (fraction of L)"),
    *[(f"heater_center_{j + 1}", c, "1", f"centre of heater {j + 1} (fraction of L)")
      for j, c in enumerate((0.2, 0.5, 0.8))],
    *[(f"sensor_position_{j + 1}", p, "1", f"position of sensor {j + 1} (fraction of L)")
      for j, p in enumerate((0.3, 0.55, 0.9))],
]
N_SUBSTEPS = 4                    # default of the Integer parameter n_substeps (Co-Simulation RK4)
STEP_SIZE = 0.25                  # DefaultExperiment stepSize [s]
INTERFACES = ("model_exchange", "co_simulation")


class BuildError(RuntimeError):
    """No C compiler, or the compilation failed (the message carries the compiler's output)."""


def compiler() -> str | None:
    """The C compiler to use: $CC, else cc, else gcc (None when there is none)."""
    for cand in ([os.environ["CC"]] if os.environ.get("CC") else []) + ["cc", "gcc"]:
        path = shutil.which(cand)
        if path:
            return path
    return None


def fmi_headers() -> Path:
    """fmpy's copy of the FMI 2.0 / 3.0 headers."""
    import fmpy

    return Path(fmpy.__file__).resolve().parent / "c-code"


def platform_folder(version: int) -> tuple[str, str]:
    """(binaries/<folder>, shared-library extension) of this machine for FMI `version`."""
    import fmpy

    return (fmpy.platform if version == 2 else fmpy.platform_tuple), fmpy.sharedLibraryExtension


# ------------------------------------------------------------------------ modelDescription
def _variables(n: int) -> list[dict]:
    """The model variables in index order: states, derivatives, inputs, outputs, parameters."""
    out = [dict(name=f"T[{i + 1}]", vr=i, causality="local", variability="continuous",
                initial="calculated", unit="F", description=f"temperature of node {i + 1}") for i in range(n)]
    out += [dict(name=f"der(T[{i + 1}])", vr=n + i, causality="local", variability="continuous",
                 initial="calculated", unit="F/s", derivative=i + 1) for i in range(n)]
    vr = 2 * n
    out += [dict(name=f"heater_{j + 1}", vr=vr + j, causality="input", variability="continuous", start=0.0,
                 unit="F/s", description=f"heater {j + 1} power (heating rate integrated over x)")
            for j in range(N_HEATERS)]
    vr += N_HEATERS
    out.append(dict(name="q_left", vr=vr, causality="input", variability="continuous", start=0.0,
                    unit="F.m/s", description="heat flux into the rod at x = 0"))
    vr += 1
    out += [dict(name=f"sensor_{j + 1}", vr=vr + j, causality="output", variability="continuous",
                 initial="calculated", unit="F", description=f"temperature at sensor {j + 1}")
            for j in range(N_SENSORS)]
    vr += N_SENSORS
    out += [dict(name=name, vr=vr + k, causality="parameter", variability="fixed", initial="exact",
                 start=start, unit=unit, description=desc) for k, (name, start, unit, desc) in enumerate(PARAMETERS)]
    vr += len(PARAMETERS)
    out.append(dict(name="n_substeps", vr=vr, type="Integer", causality="parameter", variability="fixed",
                    initial="exact", start=N_SUBSTEPS, description="RK4 steps per communication step (CS)"))
    return out


def _attrs(d: dict, keys: tuple[str, ...]) -> str:
    return "".join(f' {k}="{escape(str(d[k]))}"' for k in keys if d.get(k) is not None)


def model_description_fmi2(n: int, guid: str, interfaces: tuple[str, ...], event_indicators: int,
                           state: bool) -> str:
    variables = _variables(n)
    units = sorted({v["unit"] for v in variables if v.get("unit")})
    caps = (f' canGetAndSetFMUstate="{str(state).lower()}" canSerializeFMUstate="{str(state).lower()}"')
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             f'<fmiModelDescription fmiVersion="2.0" modelName="rod" guid="{guid}" '
             f'description="Nonlinear thermal rod, {n} nodes (sep example)" generationTool="sep build_fmu.py" '
             f'variableNamingConvention="structured" numberOfEventIndicators="{event_indicators}">']
    if "model_exchange" in interfaces:
        lines.append(f'  <ModelExchange modelIdentifier="{MODEL_IDENTIFIER}" '
                     f'completedIntegratorStepNotNeeded="true"{caps}/>')
    if "co_simulation" in interfaces:
        lines.append(f'  <CoSimulation modelIdentifier="{MODEL_IDENTIFIER}" '
                     f'canHandleVariableCommunicationStepSize="true"{caps}/>')
    lines.append("  <UnitDefinitions>")
    lines += [f'    <Unit name="{escape(u)}"/>' for u in units]
    lines.append("  </UnitDefinitions>")
    lines.append(f'  <DefaultExperiment startTime="0" stepSize="{STEP_SIZE}"/>')
    lines.append("  <ModelVariables>")
    for k, v in enumerate(variables, start=1):
        lines.append(f'    <!-- index {k} -->')
        lines.append("    <ScalarVariable" + _attrs({**v, "valueReference": v["vr"]},
                     ("name", "valueReference", "description", "causality", "variability", "initial")) + ">")
        typ = v.get("type", "Real")
        inner = _attrs(v, ("unit",) if typ == "Real" else ()) + _attrs(v, ("derivative", "start"))
        lines.append(f"      <{typ}{inner}/>")
        lines.append("    </ScalarVariable>")
    lines.append("  </ModelVariables>")
    index = {v["name"]: k for k, v in enumerate(variables, start=1)}
    states = " ".join(str(index[f"T[{i + 1}]"]) for i in range(n))
    outputs = [index[f"sensor_{j + 1}"] for j in range(N_SENSORS)]
    derivs = [index[f"der(T[{i + 1}])"] for i in range(n)]
    lines.append("  <ModelStructure>")
    lines.append("    <Outputs>")
    lines += [f'      <Unknown index="{k}" dependencies="{states}"/>' for k in outputs]
    lines.append("    </Outputs>")
    lines.append("    <Derivatives>")
    lines += [f'      <Unknown index="{k}"/>' for k in derivs]
    lines.append("    </Derivatives>")
    lines.append("    <InitialUnknowns>")
    lines += [f'      <Unknown index="{k}"/>' for k in sorted(outputs + list(range(1, n + 1)) + derivs)]
    lines.append("    </InitialUnknowns>")
    lines.append("  </ModelStructure>")
    lines.append("</fmiModelDescription>")
    return "\n".join(lines) + "\n"


def model_description_fmi3(n: int, token: str, interfaces: tuple[str, ...], state: bool) -> str:
    """FMI 3.0: T and der(T) are array variables of n elements (value references of rod_fmi3.c)."""
    caps = f' canGetAndSetFMUState="{str(state).lower()}" canSerializeFMUState="{str(state).lower()}"'
    vr_u, vr_y, vr_p = 3, 3 + N_HEATERS + 1, 3 + N_HEATERS + 1 + N_SENSORS
    units = sorted({"F", "F/s", "F.m/s"} | {u for _, _, u, _ in PARAMETERS})
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             f'<fmiModelDescription fmiVersion="3.0" modelName="rod" instantiationToken="{token}" '
             f'description="Nonlinear thermal rod, {n} nodes (sep example)" generationTool="sep build_fmu.py" '
             f'variableNamingConvention="structured">']
    if "model_exchange" in interfaces:
        lines.append(f'  <ModelExchange modelIdentifier="{MODEL_IDENTIFIER}"{caps}/>')
    if "co_simulation" in interfaces:
        lines.append(f'  <CoSimulation modelIdentifier="{MODEL_IDENTIFIER}" '
                     f'canHandleVariableCommunicationStepSize="true"{caps}/>')
    lines += ["  <UnitDefinitions>"] + [f'    <Unit name="{escape(u)}"/>' for u in units] + ["  </UnitDefinitions>"]
    lines.append(f'  <DefaultExperiment startTime="0" stepSize="{STEP_SIZE}"/>')
    lines.append("  <ModelVariables>")
    lines.append('    <Float64 name="time" valueReference="0" causality="independent" variability="continuous"/>')
    lines.append('    <Float64 name="T" valueReference="1" causality="local" variability="continuous" '
                 f'initial="calculated" unit="F"><Dimension start="{n}"/></Float64>')
    lines.append('    <Float64 name="der(T)" valueReference="2" causality="local" variability="continuous" '
                 f'initial="calculated" unit="F/s" derivative="1"><Dimension start="{n}"/></Float64>')
    for j in range(N_HEATERS):
        lines.append(f'    <Float64 name="heater_{j + 1}" valueReference="{vr_u + j}" causality="input" '
                     'variability="continuous" start="0" unit="F/s"/>')
    lines.append(f'    <Float64 name="q_left" valueReference="{vr_u + N_HEATERS}" causality="input" '
                 'variability="continuous" start="0" unit="F.m/s"/>')
    for j in range(N_SENSORS):
        lines.append(f'    <Float64 name="sensor_{j + 1}" valueReference="{vr_y + j}" causality="output" '
                     'variability="continuous" initial="calculated" unit="F"/>')
    for k, (name, start, unit, desc) in enumerate(PARAMETERS):
        lines.append(f'    <Float64 name="{name}" valueReference="{vr_p + k}" description="{escape(desc)}" '
                     f'causality="parameter" variability="fixed" start="{start}" unit="{escape(unit)}"/>')
    lines.append(f'    <Int32 name="n_substeps" valueReference="{vr_p + len(PARAMETERS)}" causality="parameter" '
                 f'variability="fixed" start="{N_SUBSTEPS}"/>')
    lines.append("  </ModelVariables>")
    lines.append("  <ModelStructure>")
    lines += [f'    <Output valueReference="{vr_y + j}" dependencies="1"/>' for j in range(N_SENSORS)]
    lines.append('    <ContinuousStateDerivative valueReference="2"/>')
    lines += ['    <InitialUnknown valueReference="1"/>', '    <InitialUnknown valueReference="2"/>']
    lines += [f'    <InitialUnknown valueReference="{vr_y + j}"/>' for j in range(N_SENSORS)]
    lines.append("  </ModelStructure>")
    lines.append("</fmiModelDescription>")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------ build
def guid_of(n: int, interfaces: tuple[str, ...], event_indicators: int, state: bool, version: int) -> str:
    """A GUID / instantiation token that changes with everything the binary depends on."""
    key = f"sep-rod n={n} if={','.join(interfaces)} ei={event_indicators} state={state} fmi={version}"
    return "{" + str(uuid.uuid5(uuid.NAMESPACE_URL, key)) + "}"


def compile_library(out: Path, n: int, guid: str, event_indicators: int, version: int) -> None:
    cc = compiler()
    if cc is None:
        raise BuildError("no C compiler found (set CC, or install cc/gcc) to build the rod FMU")
    source = SRC / f"rod_fmi{version}.c"
    cmd = [cc, "-std=c99", "-O2", "-ffp-contract=off", "-fPIC", "-shared", f"-I{fmi_headers()}", f"-I{SRC}",
           f"-DN_NODES={n}", f'-DMODEL_GUID="{guid}"', f"-DN_EVENT_INDICATORS={event_indicators}",
           str(source), "-o", str(out), "-lm"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise BuildError(f"compiling {source.name} failed:\n{' '.join(cmd)}\n{proc.stdout}{proc.stderr}")


def build_fmu(out: str | Path, *, nodes: int = 50, interfaces: tuple[str, ...] = INTERFACES,
              fmi_version: int = 2, event_indicators: int = 0, state: bool = True) -> Path:
    """Compile the rod and zip it as an FMU at `out`.

    Parameters
    ----------
    out : path of the .fmu to write (its folder is created).
    nodes : N, the number of nodes (continuous states), >= 4.
    interfaces : "model_exchange" and/or "co_simulation" (both: one binary, two interfaces).
    fmi_version : 2 or 3.
    event_indicators : event indicators to declare (the physics has none; sep refuses a Model
        Exchange FMU that declares some: a test variant).
    state : declare canGetAndSetFMUstate and canSerializeFMUstate (False: a test variant).

    Returns
    -------
    The path of the FMU.
    """
    interfaces = tuple(interfaces)
    if not interfaces or any(i not in INTERFACES for i in interfaces):
        raise ValueError(f"interfaces must be a non-empty subset of {INTERFACES}, got {interfaces!r}")
    if fmi_version not in (2, 3):
        raise ValueError(f"fmi_version must be 2 or 3, got {fmi_version!r}")
    if nodes < 4:
        raise ValueError(f"nodes must be >= 4, got {nodes}")
    out = Path(out)
    guid = guid_of(nodes, interfaces, event_indicators, state, fmi_version)
    folder, ext = platform_folder(fmi_version)
    if fmi_version == 2:
        xml = model_description_fmi2(nodes, guid, interfaces, event_indicators, state)
    elif event_indicators:
        raise ValueError("event indicators are declared in the FMI 2.0 variant only")
    else:
        xml = model_description_fmi3(nodes, guid, interfaces, state)
    with tempfile.TemporaryDirectory() as tmp:
        lib = Path(tmp) / (MODEL_IDENTIFIER + ext)
        compile_library(lib, nodes, guid, event_indicators, fmi_version)
        out.parent.mkdir(parents=True, exist_ok=True)
        partial = out.with_name(out.name + ".part")
        with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as zf:
            def add(name: str, data: bytes) -> None:
                info = zipfile.ZipInfo(name, date_time=(2020, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                info.external_attr = 0o644 << 16
                zf.writestr(info, data)

            add("modelDescription.xml", xml.encode())
            add(f"binaries/{folder}/{lib.name}", lib.read_bytes())
            for src in ("rod_model.h", f"rod_fmi{fmi_version}.c"):
                add(f"sources/{src}", (SRC / src).read_bytes())
        os.replace(partial, out)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(HERE / "rod.fmu"), help="the .fmu to write (default: %(default)s)")
    ap.add_argument("--nodes", type=int, default=50, help="nodes = continuous states (default 50)")
    ap.add_argument("--interface", choices=("both",) + INTERFACES, default="both")
    ap.add_argument("--fmi-version", type=int, choices=(2, 3), default=2)
    args = ap.parse_args(argv)
    interfaces = INTERFACES if args.interface == "both" else (args.interface,)
    try:
        path = build_fmu(args.out, nodes=args.nodes, interfaces=interfaces, fmi_version=args.fmi_version)
    except (BuildError, ValueError) as exc:
        print(f"build_fmu: error: {exc}", file=sys.stderr)
        return 2
    print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
