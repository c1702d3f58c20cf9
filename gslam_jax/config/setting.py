"""How a setting is declared: once, as a field of its section's dataclass, with its default, a
one-line meaning (``gslam config`` prints it beside the key), the rule its values meet (the
config's check and the filter's, ``rbpf.FilterConfig.validate``), the value resolved on the
host before the filter sees it, and the paper's value where the default is not the paper's."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable

__all__ = ["Setting", "setting", "setting_of", "settings_of", "UNSET"]

UNSET: Any = type("Unset", (), {"__repr__": lambda self: "UNSET"})()
"""No value: the setting has no automatic value resolved before the filter, or its default
is the paper's."""


@dataclass(frozen=True)
class Setting:
    """What is declared about one setting besides its default (the field's)."""

    doc: str
    """One line: what the setting does, its unit, and what 0 or "" means."""
    check: Callable[[Any], bool] | None = None
    """True for an allowed value (None: any value of the type)."""
    requirement: str = ""
    """The rule in words, as an error says it after the key ("must be at least 1"); ``{value}``
    is replaced by the value refused."""
    resolved: Any = UNSET
    """The automatic value the host resolves before building the filter's static config (which
    refuses it), e.g. "auto"; UNSET: none."""
    paper: Any = UNSET
    """The paper's value (``configs/paper.toml``) where the default is another; UNSET: the
    default is the paper's."""

    def allows(self, value: Any) -> bool:
        return self.check is None or bool(self.check(value))

    def refusal(self, value: Any) -> str:
        """The error's words after the key for a value ``allows`` refuses."""
        return self.requirement.replace("{value}", str(value))


def setting(default: Any, doc: str, check: Callable[[Any], bool] | None = None,
            requirement: str = "", *, one_of: tuple[str, ...] | None = None, note: str = "",
            resolved: Any = UNSET, paper: Any = UNSET) -> Any:
    """A dataclass field for one setting. ``one_of``: the allowed values of an enumerated
    setting (from ``choices``; the requirement names them, then ``note`` in brackets)."""
    if one_of is not None:
        allowed = tuple(one_of)
        check = allowed.__contains__
        requirement = f"must be one of {', '.join(allowed)}" + (f" ({note})" if note else "")
    if "\n" in doc:
        raise ValueError(f"a setting's doc is one line: {doc!r}")
    meta = Setting(doc, check, requirement, resolved, paper)
    return dataclasses.field(default=default, metadata={"setting": meta})


def settings_of(section: type | object) -> list[tuple[str, Any, Setting]]:
    """(key, default, Setting) of every field of a section class (or instance), in order."""
    cls = section if isinstance(section, type) else type(section)
    found = []
    for f in dataclasses.fields(cls):
        found.append((f.name, f.default, f.metadata["setting"]))
    return found


def setting_of(section: type | object, key: str) -> Setting:
    """The Setting declared for ``key`` of a section class (or instance)."""
    cls = section if isinstance(section, type) else type(section)
    return {f.name: f for f in dataclasses.fields(cls)}[key].metadata["setting"]
