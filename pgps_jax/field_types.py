"""Whether a value is of a settings field's type, strictly (no conversion).

The type check behind the refusals of `envs.physics.Physics` and `cli.run_config.coerce`, and
the words of their messages.
"""

import numbers
import typing
from typing import Any, Optional

_WORDS = {int: "an integer", bool: "true or false", str: "a string",
          Optional[bool]: "true, false or None"}


def mismatch(value: Any, kind: Any) -> Optional[str]:
    """None if `value` is of the field type `kind`, else what such a value must be, in words.

    `int`: an integer, not a bool; `bool`: a bool; `str`: a string; `Optional[bool]`: a bool
    or None. TypeError for any other type.
    """
    if kind not in _WORDS:
        raise TypeError(f"unsupported field type {kind}")
    optional = typing.get_origin(kind) is typing.Union
    if optional and value is None:
        return None
    base = typing.get_args(kind)[0] if optional else kind
    if base is int:
        valid = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    else:
        valid = isinstance(value, base)
    return None if valid else _WORDS[kind]
