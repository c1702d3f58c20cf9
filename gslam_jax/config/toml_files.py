"""Config files: TOML text to a checked ``Config`` and back, ``--set`` overrides, and the
layers a command runs with (defaults, the file's shared sections, its
``[course.<name>.<section>]`` tables for a simulated course, then the overrides)."""

from __future__ import annotations

import dataclasses
import tomllib
from collections.abc import Collection
from pathlib import Path
from typing import Any

from gslam_jax.config.sections import SECTION_TYPES, Config, ConfigError
from gslam_jax.config.setting import UNSET, Setting, settings_of

__all__ = ["read_toml", "load_config", "parse_config", "apply_overrides", "section_to_toml",
           "config_to_toml", "key_comment", "COMMENTED_HEADER", "load_table_config",
           "layered_config"]


def _coerce(value: Any, expected: type, where: str) -> Any:
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        try:
            return float(value)
        except OverflowError:
            raise ConfigError(f"{where}: {value} is too large for a float") from None
    if expected is tuple:  # a matrix: 16 numbers, or 4 rows of 4 (flattened, row-major)
        rows = value if isinstance(value, list) else None
        if rows and all(isinstance(r, list) for r in rows):
            if len(rows) != 4 or any(len(r) != 4 for r in rows):
                raise ConfigError(f"{where}: expected 4 rows of 4 numbers")
            rows = [v for r in rows for v in r]
        if rows is None or len(rows) not in (0, 16):
            raise ConfigError(f"{where}: expected 16 numbers or 4 rows of 4, got {value!r}")
        return tuple(_coerce(v, float, where) for v in rows)
    if expected is int and isinstance(value, bool):
        raise ConfigError(f"{where}: expected int, got bool")
    if not isinstance(value, expected):
        raise ConfigError(f"{where}: expected {expected.__name__}, got {type(value).__name__} "
                          f"({value!r})")
    return value


def parse_config(data: dict[str, Any], source: str = "<config>",
                 base: Config | None = None) -> Config:
    """Build a Config from a parsed TOML table, checking every section, key and type."""
    base = base or Config()
    sections = {}
    for name, table in data.items():
        if name not in SECTION_TYPES:
            raise ConfigError(f"{source}: unknown section [{name}]; known sections: "
                              f"{', '.join(SECTION_TYPES)}")
        if not isinstance(table, dict):
            raise ConfigError(f"{source}: [{name}] must be a table")
        cls = SECTION_TYPES[name]
        types = {f.name: f.type for f in dataclasses.fields(cls)}
        values = {}
        for key, value in table.items():
            if key not in types:
                raise ConfigError(f"{source}: unknown key '{key}' in [{name}]; known keys: "
                                  f"{', '.join(types)}")
            expected = {"int": int, "float": float, "str": str, "bool": bool,
                        "tuple[float, ...]": tuple}[types[key]]
            values[key] = _coerce(value, expected, f"{source}: [{name}] {key}")
        sections[name] = dataclasses.replace(getattr(base, name), **values)
    return dataclasses.replace(base, **sections).validate(source)


def read_toml(path: str | Path) -> dict[str, Any]:
    """A config file's TOML table; a missing or empty file or bad TOML is a ConfigError naming
    it."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"{path}: no such config file")
    try:
        text = path.read_text(encoding="utf-8")
        if not text.strip():  # e.g. left by a write that failed: not "all defaults" silently
            raise ConfigError(f"{path}: the config file is empty; give the settings it should "
                              "hold, or leave out --config for the defaults")
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: malformed TOML: {err}") from err
    except UnicodeDecodeError as err:
        line = path.read_bytes()[:err.start].count(b"\n") + 1
        raise ConfigError(f"{path}:{line}: not UTF-8 text (byte 0x{err.object[err.start]:02x}; "
                          "TOML files must be UTF-8)") from err
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the config file ({err.strerror or err})") from err


def load_config(path: str | Path | None) -> Config:
    """Defaults, or a TOML file over the defaults."""
    if path is None:
        return Config()
    return parse_config(read_toml(path), str(path))


def apply_overrides(config: Config, overrides: list[str]) -> Config:
    """Apply ``section.key=value`` strings (value parsed as TOML, bare words as strings)."""
    data: dict[str, dict[str, Any]] = {}
    for item in overrides:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise ConfigError(f"--set {item!r}: expected section.key=value")
        lhs, rhs = item.split("=", 1)
        section, key = lhs.strip().split(".", 1)
        try:
            value = tomllib.loads(f"v = {rhs.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = rhs.strip()
        data.setdefault(section, {})[key] = value
    return parse_config(data, "--set", base=config)


def _toml_value(value: Any) -> str:
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):  # a matrix: 4 rows of 4, or []
        rows = [value[i:i + 4] for i in range(0, len(value), 4)]
        return f"[{', '.join(str(list(r)) for r in rows)}]"
    return repr(value)


def key_comment(rule: Setting) -> str:
    """The one-line comment ``gslam config`` prints beside a key: its declared meaning, and the
    paper's value where the default is another."""
    paper = "" if rule.paper is UNSET else f"; the paper's: {_toml_value(rule.paper)}"
    return rule.doc + paper


def section_to_toml(config: Config, name: str, comments: bool = False) -> str:
    """One section of the config (``name``: filter, motion, ...) as a TOML table; with
    ``comments`` each key followed by its ``key_comment``."""
    section = getattr(config, name)
    lines = [f"[{name}]"]
    for key, _, rule in settings_of(section):
        line = f"{key} = {_toml_value(getattr(section, key))}"
        lines.append(f"{line}  # {key_comment(rule)}" if comments else line)
    return "\n".join(lines) + "\n"


def config_to_toml(config: Config, comments: bool = False) -> str:
    """The full config as TOML text (written bare beside every run's results; with
    ``comments``, as ``gslam config`` prints it, each key with its one-line meaning)."""
    text = "\n".join(section_to_toml(config, name, comments) for name in SECTION_TYPES)
    return (COMMENTED_HEADER + text) if comments else text


COMMENTED_HEADER = ("# gslam's settings, each key with what it means (docs/configuration.md);\n"
                    "# where a default is not the paper's, its comment gives the paper's value\n"
                    "# (configs/paper.toml).\n")
"""The lines ``config_to_toml(..., comments=True)`` starts with."""


def load_table_config(path: str | Path | None, courses: Collection[str] = ()
                      ) -> tuple[Config, dict[str, Config]]:
    """The shared config and per-course configs of a Table I TOML file.

    Besides the usual sections, the file may hold ``[course.<name>.<section>]`` tables whose
    keys override the shared settings for that course only, as the paper tuned its noise
    parameters per environment (7.3); ``courses``: the names such a table may have (the
    simulator's, ``sim.courses.COURSES``). Other names are errors that name the file.
    """
    if path is None:
        return Config(), {}
    data = read_toml(path)
    per_course = data.pop("course", {})
    base = parse_config(data, str(path))
    if not isinstance(per_course, dict):
        raise ConfigError(f"{path}: [course] must be a table of [course.<name>.<section>] tables")
    configs = {}
    for name, table in per_course.items():
        if name not in courses:
            known = ", ".join(courses) or "none (this command reads no course tables)"
            raise ConfigError(f"{path}: unknown course [course.{name}]; known courses: {known}")
        if not isinstance(table, dict):
            raise ConfigError(f"{path}: [course.{name}] must be a table of sections")
        configs[name] = parse_config(table, f"{path} [course.{name}]", base=base)
    return base, configs


def layered_config(path: str | Path | None, course: str | None = None,
                   overrides: list[str] | None = None, courses: Collection[str] = ()) -> Config:
    """The config a command runs with: defaults, the file at ``path`` (its shared sections and,
    for the simulated ``course``, that course's ``[course.<name>.*]`` tables; None: no course
    tables), then the ``section.key=value`` ``overrides``. ``courses``: the names a
    ``[course.<name>]`` table may have (``load_table_config``)."""
    shared, per_course = load_table_config(path, courses)
    config = per_course.get(course, shared) if course is not None else shared
    return apply_overrides(config, overrides or [])
