"""The one style of a configuration error: ``<dotted key> must be <allowed>, got <value>``.

Every config dataclass (``PPOConfig``, ``SimConfig``, the trainer's sections) checks its values with
:func:`require` under the key a user types: ``agent.lr must be > 0, got -1`` from the command line,
``PPOConfig.lr must be > 0, got -1`` from Python.
"""

from __future__ import annotations


def require(ok: bool, key: str, allowed: str, value: object) -> None:
    """Raise ``ValueError(f"{key} must be {allowed}, got {value!r}")`` unless ``ok``."""
    if not ok:
        raise ValueError(f"{key} must be {allowed}, got {value!r}")


def is_int(value: object, minimum: int) -> bool:
    """An int (not a bool) >= ``minimum``."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= minimum


def is_number(value: object) -> bool:
    """An int or float (not a bool)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)
