"""Typed, strict configuration: dataclass schemas loaded from YAML through OmegaConf structured configs.

Every component declares its configuration as a ``@dataclass`` with a docstring on each field and its unit.
:func:`load_config` merges, in order, the schema defaults, zero or more YAML files and dotted ``a.b=value``
overrides. Unknown keys and ill-typed values raise :class:`ConfigError` naming the full dotted path, before
any work starts (the same contract as ml_collections' ``lock()``). The caller's objects are never mutated.

This module lives in ``envs`` because ``envs`` may not import ``shield_nav``; ``shield_nav`` reuses it.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable, Mapping
from typing import Any, TypeVar

import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException
from omegaconf.nodes import BooleanNode

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration value or key is invalid. The message names the full dotted key path."""


def _format_omegaconf_error(err: OmegaConfBaseException, source: str) -> str:
    key = getattr(err, "full_key", None) or getattr(err, "key", None)
    msg = (getattr(err, "msg", None) or str(err)).strip().splitlines()[0]
    where = f" (from {source})" if source else ""
    if key:
        return f"config key '{key}'{where}: {msg}"
    return f"config{where}: {msg}"


def _check_bools(base: DictConfig, other: Any, source: str, prefix: str = "") -> None:
    """Refuse a non-boolean value for a boolean key of ``base`` in the layer ``other``.

    OmegaConf turns any integer into a boolean (``fence=3`` would read as true), so a typed layer checks its
    booleans itself: YAML's true / false (and yes / no, on / off) pass; a number or a string is refused by name.
    """
    if not isinstance(other, DictConfig) or not isinstance(base, DictConfig):
        return
    for key in other:
        if key not in base:
            continue  # an unknown key: the merge names it
        node, raw = base._get_node(key), other._get_node(key)
        if isinstance(node, DictConfig):
            _check_bools(node, raw, source, f"{prefix}{key}.")
        elif isinstance(node, BooleanNode):
            value = raw._value() if raw is not None else None
            if value is not None and not isinstance(value, bool) and not _is_interpolation(value):
                where = f" (from {source})" if source else ""
                raise ConfigError(f"config key '{prefix}{key}'{where}: must be true or false, got {value!r}")


def _is_interpolation(value: Any) -> bool:
    return isinstance(value, str) and value.startswith("${")


def _merge(base: DictConfig, other: Any, source: str) -> DictConfig:
    _check_bools(base, other, source)
    try:
        return OmegaConf.merge(base, other)
    except OmegaConfBaseException as err:
        raise ConfigError(_format_omegaconf_error(err, source)) from None


def load_config(
    schema: type[T],
    files: Iterable[str | os.PathLike] | str | os.PathLike | None = None,
    overrides: Iterable[str] | Mapping[str, Any] | None = None,
    base: T | None = None,
) -> T:
    """Build a validated config object of type ``schema``.

    Args:
        schema: A dataclass type (the schema). Its defaults are the base layer.
        files: YAML file(s) merged on top, in order. A YAML file may hold a top-level ``defaults: [file, ...]``
            list of other YAML files (relative to itself) merged before its own content.
        overrides: Dotted overrides, either ``["a.b=1", ...]`` or a mapping ``{"a.b": 1}``, merged last.
        base: An existing config object of type ``schema`` to start from instead of the schema defaults.

    Returns:
        An instance of ``schema`` (a fresh object; nothing passed in is mutated).

    Raises:
        ConfigError: On an unknown key, a value of the wrong type, a missing required value, or a bad file.
    """
    cfg = OmegaConf.structured(schema if base is None else base)
    if files is not None:
        if isinstance(files, (str, os.PathLike)):
            files = [files]
        for path in files:
            cfg = _merge(cfg, _read_yaml_with_defaults(path), str(path))
    if overrides:
        cfg = _merge(cfg, _overrides_config(overrides), "overrides")
    missing = sorted(OmegaConf.missing_keys(cfg))
    if missing:
        raise ConfigError(f"config key '{missing[0]}' is required but was not set")
    try:
        obj = OmegaConf.to_object(cfg)
    except OmegaConfBaseException as err:
        raise ConfigError(_format_omegaconf_error(err, "")) from None
    validate(obj)
    return obj  # type: ignore[return-value]


def _overrides_config(overrides: Iterable[str] | Mapping[str, Any]) -> DictConfig:
    """Dotted overrides (``["a.b=1"]`` or ``{"a.b": 1}``) as one untyped config layer."""
    try:
        if isinstance(overrides, Mapping):
            dot = OmegaConf.create()
            for k, v in overrides.items():
                OmegaConf.update(dot, k, v, force_add=True)
            return dot
        items = list(overrides)
        for item in items:
            if "=" not in item:
                raise ConfigError(f"override '{item}' is not of the form a.b=value")
            try:
                OmegaConf.from_dotlist([item])
            except yaml.YAMLError as err:  # the value is parsed as YAML: name the item, not the parser's position
                raise ConfigError(f"override '{item}': its value is not valid YAML ({str(err).splitlines()[0]}); "
                                  "quote an item of a list that itself holds commas or brackets, e.g. "
                                  "\"env_overrides=[a=1,'b=[0,0]']\"") from None  # fmt: skip
        return OmegaConf.from_dotlist(items)
    except OmegaConfBaseException as err:
        raise ConfigError(_format_omegaconf_error(err, "overrides")) from None


def select_raw(
    key: str,
    files: Iterable[str | os.PathLike] | str | os.PathLike | None = None,
    overrides: Iterable[str] | Mapping[str, Any] | None = None,
    default: Any = None,
) -> Any:
    """The value the layers give the dotted ``key``, read before any schema applies.

    ``default`` where no layer sets it. For schemas whose shape depends on a value, e.g. an algorithm section typed
    by its ``class_name``.
    """
    raw = OmegaConf.create()
    if files is not None:
        for path in [files] if isinstance(files, (str, os.PathLike)) else files:
            raw = OmegaConf.merge(raw, _read_yaml_with_defaults(path))
    if overrides:
        raw = OmegaConf.merge(raw, _overrides_config(overrides))
    return OmegaConf.select(raw, key, default=default)


def _read_yaml_with_defaults(path: str | os.PathLike, _seen: tuple[str, ...] = ()) -> DictConfig:
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ConfigError(f"config file '{path}' does not exist")
    real = os.path.realpath(path)
    if real in _seen:
        raise ConfigError(f"config file '{path}' includes itself through 'defaults'")
    try:
        raw = OmegaConf.load(path)
    except Exception as err:  # yaml errors are not OmegaConf errors
        raise ConfigError(f"config file '{path}' could not be parsed: {err}") from None
    if not isinstance(raw, DictConfig):
        raise ConfigError(f"config file '{path}' must hold a mapping at the top level")
    out = OmegaConf.create()
    if "defaults" in raw:
        bases = raw.pop("defaults")
        if isinstance(bases, str):
            bases = [bases]
        for base in bases:
            base_path = os.path.join(os.path.dirname(path), str(base))
            out = OmegaConf.merge(out, _read_yaml_with_defaults(base_path, (*_seen, real)))
    return OmegaConf.merge(out, raw)


def validate(obj: Any, prefix: str = "") -> None:
    """Call ``obj.validate(prefix)`` on every nested dataclass that defines it (depth first)."""
    if not dataclasses.is_dataclass(obj):
        return
    for f in dataclasses.fields(obj):
        validate(getattr(obj, f.name), f"{prefix}{f.name}.")
    check = getattr(obj, "validate", None)
    if callable(check):
        check(prefix)


def stored_config(cls: type, raw: Mapping[str, Any]) -> dict:
    """A config dict that an earlier version wrote (a checkpoint's, a run folder's), as that version meant it.

    A field added later takes its default when absent, and a new field's default normally keeps the behaviour from
    before it. Where it does not, its dataclass names it in ``PRE_FIELD_VALUES`` (a class-level dict of field name
    to the value that reproduces the earlier behaviour), and an absent field takes that value instead. Walks nested
    dataclass fields (e.g. ``runner.expert.params.expert``). Returns a new dict; ``raw`` is left as it is.
    """
    out = dict(raw)
    inst = cls()
    for f in dataclasses.fields(cls):
        if f.name not in out:
            pre = getattr(cls, "PRE_FIELD_VALUES", {})
            if f.name in pre:
                out[f.name] = pre[f.name]
            continue
        sub = getattr(inst, f.name)
        if dataclasses.is_dataclass(sub) and isinstance(out[f.name], Mapping):
            out[f.name] = stored_config(type(sub), out[f.name])
    return out


def to_dict(obj: Any) -> dict:
    """A plain (YAML/JSON-able) dict of a config dataclass."""
    return OmegaConf.to_container(OmegaConf.structured(obj), resolve=True)  # type: ignore[return-value]


def to_yaml(obj: Any) -> str:
    """The YAML text of a config dataclass (what a run folder stores as its resolved config)."""
    return OmegaConf.to_yaml(OmegaConf.structured(obj))


def require(cond: bool, key: str, msg: str) -> None:
    """Raise :class:`ConfigError` naming ``key`` unless ``cond`` holds (for ``validate`` methods)."""
    if not cond:
        raise ConfigError(f"config key '{key}': {msg}")
