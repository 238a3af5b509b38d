"""Config files: layers of YAML merged over the defaults and validated, one-line errors
that name the key and its nearest valid spelling, the resolved config saved, and the
defaults written as ``configs/default.yaml``."""

from __future__ import annotations

import difflib
from pathlib import Path
from typing import Any, get_args

import yaml
from pydantic import BaseModel, ValidationError

from gtgen.config.root import GtgenConfig
from gtgen.config.synth import EASY_WORLD, SynthConfig
from gtgen.errors import ConfigError, InputNotFoundError


def configs_dir() -> Path:
    """Return the project's ``configs/`` folder (YAML only)."""
    return Path(__file__).resolve().parents[2] / "configs"


# mappings a config layer gives whole: a robot's cameras replace the default rig, they do
# not join it (a layer that names two cameras means two)
WHOLE = {("topics", "cameras")}


def _deep_merge(base: dict[str, Any], over: dict[str, Any], at: tuple[str, ...] = ()) -> dict[str, Any]:
    out = dict(base)
    for key, val in over.items():
        if isinstance(val, dict) and isinstance(out.get(key), dict) and (*at, key) not in WHOLE:
            out[key] = _deep_merge(out[key], val, (*at, key))
        else:
            out[key] = val
    return out


def _world_layer(layer: dict[str, Any]) -> dict[str, Any]:
    """Return ``layer`` with the keys its ``synth.world`` implies where it does not set them
    (the easy world's values, or the paper world's defaults), so a later layer's world
    replaces an earlier one's."""
    synth = layer.get("synth")
    if not isinstance(synth, dict) or synth.get("world") not in ("easy", "paper"):
        return layer
    base = EASY_WORLD if synth["world"] == "easy" else {k: SynthConfig.model_fields[k].default for k in EASY_WORLD}
    return {**layer, "synth": {**base, **synth}}


def _format_validation(err: ValidationError) -> str:
    errors = err.errors()
    # a misspelt key is also a missing one (topics.cameras.front: 'imag' and no 'image'):
    # the unknown key is the one to name, with its nearest valid spelling
    first = next((e for e in errors if e["type"] == "extra_forbidden"), errors[0])
    parts = tuple(str(p) for p in first["loc"])
    loc = ".".join(parts) or "<root>"
    more = f" (and {err.error_count() - 1} more)" if err.error_count() > 1 else ""
    if first["type"] == "extra_forbidden":
        return f"config key '{loc}' is not a gtgen setting; {_nearest_key(parts)}{more}"
    if first["type"] == "value_error":  # a validator's own message names the keys and values
        msg = first["msg"].removeprefix("Value error, ")
        return f"config: {msg}{more}" if loc == "<root>" else f"config key '{loc}': {msg}{more}"
    val = first.get("input")
    shown = "" if isinstance(val, dict) else f" = {val!r}"
    return f"config key '{loc}'{shown}: {first['msg']}{more}"


def _nearest_key(parts: tuple[str, ...]) -> str:
    """Return 'did you mean ...?' with the valid key nearest the unknown ``parts``, or the
    keys its section takes."""
    model: type[BaseModel] = GtgenConfig
    path: list[str] = []
    rest = list(parts[:-1])
    while rest:
        name = rest.pop(0)
        ann = model.model_fields[name].annotation
        path.append(name)
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            model = ann
        else:  # a mapping of models (topics.cameras): the next part is its key
            model = get_args(ann)[-1]
            path.append(rest.pop(0))
    prefix = "".join(f"{p}." for p in path)
    keys = list(model.model_fields)
    near = difflib.get_close_matches(parts[-1], keys, n=1, cutoff=0.6)
    if near:
        return f"did you mean '{prefix}{near[0]}'?"
    return f"{prefix.rstrip('.') or 'the top level'} takes: {', '.join(keys)}"


def read_yaml(path: Path, what: str = "config file") -> dict[str, Any]:
    """Return the mapping in YAML file ``path`` (``what`` names the file in errors)."""
    if not path.exists():
        raise InputNotFoundError(f"{what} '{path}' does not exist")
    if not path.is_file():
        raise ConfigError(f"{what} '{path}' is a folder; expected a YAML file")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except UnicodeDecodeError as err:
        raise ConfigError(f"{what} '{path}' is not a text file: byte {err.start} is not UTF-8") from err
    except yaml.YAMLError as err:
        raise ConfigError(f"{what} '{path}' is not valid YAML: {_yaml_problem(err)}") from err
    if not isinstance(data, dict):
        raise ConfigError(f"{what} '{path}' must hold a mapping of keys to values, got a {type(data).__name__}")
    return data


def _yaml_problem(err: yaml.YAMLError) -> str:
    problem = getattr(err, "problem", None) or str(err).splitlines()[0]
    mark = getattr(err, "problem_mark", None)
    return problem + (f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else "")


def check_value(key: str, value: Any) -> Any:
    """Return ``value`` as config key ``key`` ('section.name') takes it; raise ConfigError
    saying what the key takes (a command-line option is held to its key's bounds)."""
    section, name = key.split(".")
    model = getattr(GtgenConfig(), section)
    try:
        setattr(model, name, value)
    except ValidationError as err:
        first = err.errors()[0]
        raise ConfigError(f"{value!r} is not a valid {key}: {first['msg']}") from err
    return getattr(model, name)


def build_config(*layers: dict[str, Any]) -> GtgenConfig:
    """Return the defaults overridden by each partial mapping in ``layers``, in order."""
    merged: dict[str, Any] = GtgenConfig().model_dump(mode="json")
    for layer in layers:
        merged = _deep_merge(merged, _world_layer(layer))
    try:
        return GtgenConfig.model_validate(merged)
    except ValidationError as err:
        raise ConfigError(_format_validation(err)) from err


def stored_config(data: dict[str, Any], source: str, sections: tuple[str, ...] = ()) -> GtgenConfig:
    """Return the resolved config a store or checkpoint recorded (``source`` names it in
    the error): its ``sections`` (all but ``train`` when empty), the others at their
    defaults. The ``train`` section is always left out: how the maker of a dataset would
    train says nothing about the data, and trainer keys change between versions, so a
    dataset stays readable by a gtgen whose trainer has other keys; so are the sections of
    stages after a store's. Raises ConfigError, one line, for any key of those sections
    this gtgen does not accept."""
    try:
        return GtgenConfig.model_validate({k: v for k, v in data.items() if k != "train" and (not sections or k in sections)})
    except ValidationError as err:
        raise ConfigError(f"{source} records a config this gtgen does not accept ({_format_validation(err)}); "
                          "rebuild it with this version") from err


def load_config(path: Path | None = None, *overrides: dict[str, Any]) -> GtgenConfig:
    """Return the defaults, overridden by YAML file ``path`` and then by ``overrides``."""
    layers = [read_yaml(path)] if path is not None else []
    return build_config(*layers, *overrides)


def save_config(cfg: GtgenConfig, path: Path, overwrite: bool = False) -> None:
    """Write the resolved ``cfg`` as YAML to ``path`` (atomically; the signature in its first
    line; a file there that gtgen did not write only with ``overwrite``)."""
    from gtgen.runtime.output import signature, write_atomic

    write_atomic(path, f"# {signature()}: the resolved config\n" + yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False), overwrite)


def default_yaml() -> str:
    """Return the defaults as YAML with each field's description (and unit) as a comment."""
    lines = ["# gtgen defaults: every key, its unit and meaning. A --config file overrides any subset.", ""]

    def walk(model: type[BaseModel], value: BaseModel, indent: int) -> None:
        pad = "  " * indent
        for name, field in model.model_fields.items():
            v = getattr(value, name)
            desc = field.description or ""
            if isinstance(v, BaseModel):
                lines.append(f"{pad}{name}:" + (f"  # {desc}" if desc else ""))
                walk(type(v), v, indent + 1)
            elif isinstance(v, dict) and v and isinstance(next(iter(v.values())), BaseModel):
                lines.append(f"{pad}{name}:" + (f"  # {desc}" if desc else ""))
                for k, sub in v.items():
                    lines.append(f"{pad}  {k}:")
                    walk(type(sub), sub, indent + 2)
            else:
                dumped = yaml.safe_dump({name: v}, default_flow_style=True, width=1000).strip()[1:-1]
                lines.append(f"{pad}{dumped}" + (f"  # {desc}" if desc else ""))

    cfg = GtgenConfig()
    for name in GtgenConfig.model_fields:
        sub = getattr(cfg, name)
        lines.append(f"{name}:  # {(type(sub).__doc__ or '').strip().splitlines()[0]}")
        walk(type(sub), sub, 1)
        lines.append("")
    return "\n".join(lines)
