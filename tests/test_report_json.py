"""report.json's writer (export.dumps_report): plain JSON that reads back as the report, short number lists on one
line."""

import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volpuzzle.export import dumps_report

_SCALARS = (st.none() | st.booleans() | st.integers(-10**20, 10**20) | st.floats(allow_nan=False, allow_infinity=False)
            | st.text(max_size=8))
_VALUES = st.recursive(_SCALARS, lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=5), inner,
                                                                                             max_size=5), max_leaves=30)


@settings(max_examples=200, deadline=None)
@given(_VALUES)
def test_the_report_reads_back_as_it_was_written(value):
    text = dumps_report(value)
    assert json.loads(text) == value
    assert text == dumps_report(json.loads(text))


def test_strings_and_numbers_are_written_as_json_writes_them():
    values = ["p0-0-0", "ünïcode\t", 1e-300, -0.0, 12345678901234567890, True, None, 1.5, "x" * 60]
    text = dumps_report({"é\n\"id\"": values})
    expected = ",\n".join("    " + json.dumps(v) for v in values)
    assert text == '{\n  "\\u00e9\\n\\"id\\"": [\n' + expected + "\n  ]\n}"


def test_short_number_lists_stay_on_one_line_and_long_ones_are_broken():
    text = dumps_report({"bbox_mm": [[0.5, 1, 2], [3, 4, 5.25]], "long": list(range(40))})
    assert '"bbox_mm": [[0.5, 1, 2], [3, 4, 5.25]]' in text
    assert '"long": [\n    0,\n    1,' in text


@pytest.mark.parametrize("bad", [math.nan, math.inf, [1.0, -math.inf], {"a": {"b": math.nan}}])
def test_a_value_json_cannot_hold_is_refused(bad):
    with pytest.raises(ValueError, match="Out of range float values are not JSON compliant"):
        dumps_report(bad)
