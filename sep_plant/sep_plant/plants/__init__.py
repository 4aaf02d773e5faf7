"""Plant registry: the built-in plants, plants installed under the ``sep.plants`` entry-point
group, and any class named as ``"package.module:ClassName"``.

    make_plant("slab", {"n_x": 200})                     # built-in
    make_plant("burgers", {...})                         # an installed entry point
    make_plant("my_pkg.furnace:Furnace", {...})          # an importable class
    make_plant("fmu", {"path": "model.fmu", ...})        # an FMU (sep_plant.plants.fmu)

A type string resolves in that order. Constructing a plant runs its own key checks; every
failure is a `PlantTypeError` / `PlantConfigError` whose message names the type and the key.
"""
from __future__ import annotations

import importlib
from typing import Any, Mapping

from sep_plant.plants.keys import PlantConfigError

ENTRY_POINT_GROUP = "sep.plants"

#: built-in plant types -> "module:Class" (imported on first use)
BUILTIN: dict[str, str] = {
    "slab": "sep_plant.plants.slab:SlabPlant",
    "plate": "sep_plant.plants.heat:HeatPlate",
    "block": "sep_plant.plants.heat:HeatBlock",
    "allen_cahn": "sep_plant.plants.allen_cahn:AllenCahnPlant",
    "fmu": "sep_plant.plants.fmu.plant:FMUPlant",
    "gym": "sep_plant.plants.gym:GymPlant",
    "controlgym": "sep_plant.plants.controlgym:ControlgymPlant",
}


class PlantTypeError(ValueError):
    """A plant type string names nothing that can be loaded."""


def _entry_points() -> dict[str, Any]:
    from importlib.metadata import entry_points

    try:
        return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}
    except Exception:  # noqa: BLE001 - broken metadata of some other distribution
        return {}


def available() -> dict[str, str]:
    """Every plant type name this installation knows: built-ins and entry points -> target."""
    out = dict(BUILTIN)
    for name, ep in _entry_points().items():
        out.setdefault(name, ep.value)
    return out


def import_target(target: str, what: str, error: type[Exception] = PlantTypeError) -> Any:
    """The callable named ``"package.module:attr"`` (a plant class or factory, an env factory);
    `error` (naming `what`) when it cannot be imported or is not callable."""
    module, _, attr = target.partition(":")
    if not module or not attr:
        raise error(f"{what}: expected 'package.module:ClassName', got {target!r}")
    try:
        mod = importlib.import_module(module)
    except ImportError as exc:
        raise error(f"{what}: cannot import module {module!r} ({exc}); install the package "
                    "that provides it or put it on PYTHONPATH") from None
    obj: Any = mod
    for part in attr.split("."):
        obj = getattr(obj, part, None)
        if obj is None:
            raise error(f"{what}: module {module!r} has no {attr!r}")
    if not callable(obj):
        raise error(f"{what}: {target!r} is not a class or factory")
    return obj


def resolve(type_name: str) -> type:
    """The plant class (or factory) of a type string."""
    if not isinstance(type_name, str) or not type_name.strip():
        raise PlantTypeError(f"plant type must be a non-empty string, got {type_name!r}")
    name = type_name.strip()
    if name in BUILTIN:
        return import_target(BUILTIN[name], f"built-in plant {name!r}")
    eps = _entry_points()
    if name in eps:
        try:
            return eps[name].load()
        except Exception as exc:  # noqa: BLE001 - a broken plugin must not look like a typo
            raise PlantTypeError(f"plant {name!r} (entry point {eps[name].value!r} in group "
                                 f"{ENTRY_POINT_GROUP!r}) failed to load: {type(exc).__name__}: {exc}") from None
    if ":" in name:
        return import_target(name, f"plant {name!r}")
    known = ", ".join(sorted(available()))
    raise PlantTypeError(f"unknown plant type {name!r}: known types are {known}; or give "
                         "'package.module:ClassName', or register an entry point in group "
                         f"{ENTRY_POINT_GROUP!r}")


def make_plant(type_name: str, config: Mapping[str, Any] | None = None):
    """Construct a plant of `type_name` from its own keys."""
    cls = resolve(type_name)
    kwargs = dict(config or {})
    bad = [k for k in kwargs if not isinstance(k, str)]
    if bad:
        raise PlantConfigError(f"plant {type_name!r}: keys must be strings, got {bad!r}")
    try:
        return cls(**kwargs)
    except PlantConfigError as exc:
        raise PlantConfigError(f"plant {type_name!r}: {exc}") from None
    except TypeError as exc:
        # unexpected keyword argument / missing argument: name the accepted keys
        raise PlantConfigError(f"plant {type_name!r}: {exc}{_accepted(cls)}") from None
    except ValueError as exc:
        raise PlantConfigError(f"plant {type_name!r}: {exc}") from None


def type_name_of(plant: Any) -> str:
    """The type string that rebuilds `plant`: its built-in or entry-point name, else module:Class
    (of the plant a `sep_plant.device.DevicePlant` wraps)."""
    from sep_plant.device import base_plant

    cls = type(base_plant(plant))
    target = f"{cls.__module__}:{cls.__qualname__}"
    for name, tgt in available().items():
        if tgt == target:
            return name
    return target


def _accepted(cls) -> str:
    import inspect

    try:
        params = [p for p in inspect.signature(cls).parameters if p not in ("self", "args", "kwargs")]
    except (TypeError, ValueError):
        return ""
    return f" (accepted keys: {', '.join(params)})" if params else ""


__all__ = ["BUILTIN", "ENTRY_POINT_GROUP", "PlantConfigError", "PlantTypeError", "available", "import_target", "make_plant",
           "resolve", "type_name_of"]
