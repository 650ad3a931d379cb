"""field_types.mismatch: the strict check of a value against a settings field's type."""

from typing import Optional

import numpy as np
import pytest

from pgps_jax.field_types import mismatch


@pytest.mark.parametrize("value, kind", [
    (2, int), (np.int64(2), int), (True, bool), (False, bool), ("rk4", str),
    (None, Optional[bool]), (True, Optional[bool])])
def test_a_value_of_the_field_s_type_passes(value, kind):
    assert mismatch(value, kind) is None


@pytest.mark.parametrize("value, kind, words", [
    (2.0, int, "an integer"), (True, int, "an integer"), ("2", int, "an integer"),
    (0, bool, "true or false"), (np.bool_(True), bool, "true or false"),
    (None, bool, "true or false"), (3, str, "a string"),
    (1, Optional[bool], "true, false or None")])
def test_a_value_of_another_type_is_named_by_what_it_must_be(value, kind, words):
    assert mismatch(value, kind) == words


def test_a_field_type_without_a_check_is_refused():
    with pytest.raises(TypeError, match="unsupported field type"):
        mismatch(2.0, float)
