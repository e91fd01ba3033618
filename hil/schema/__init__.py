"""The scenario schema: every key of every scenario section declared once, as data, and the
one-line errors generated from the declarations.

A section is a frozen dataclass whose fields are declared with `setting` (type and default from
the field; unit, range, choices, pattern and a one-line description in its `Key`), and whose
class attribute `RULES` holds the rules between keys (`Needs`: "a < b", "x requires y", "one
of", under a condition; `Multiple`; `Check`, a rule that is code); a table the code keeps as a
dict (`[robot.gripper]`) is a `Table` of `Key`s, listed in its section's `TABLES`. `build` turns
a parsed TOML table into a section (unknown keys, types, required keys), `check` judges the
built values, and `hil.scenario_reference` writes the reference of every key from the same
declarations (`hil scenarios --keys`, docs/scenario-keys.md).

Invariant: a message is one line, `FILE: KEY: must ..., got VALUE` (the type errors and
`Multiple`'s say it their way), generated from the declaration that failed; the first failure
is reported: each key's own checks whose bounds are constants, then the ranges bounded by other
keys, then the rules, each in the order declared.
"""

from hil.schema.build import build, convert, type_text
from hil.schema.checking import check, sections
from hil.schema.conditions import (
    Bound,
    Computed,
    Condition,
    Dbc,
    Given,
    Is,
    MinItems,
    OneOf,
    Pattern,
    Range,
    Ref,
    bound_text,
    fraction,
    not_negative,
    positive,
)
from hil.schema.keys import (
    INTERNAL,
    REQUIRED,
    Check,
    Key,
    Multiple,
    Needs,
    RobotSection,
    Rule,
    Table,
    keys_of,
    setting,
)
from hil.schema.messages import Context, fail, got, number, shown

__all__ = [
    "INTERNAL",
    "REQUIRED",
    "Bound",
    "Check",
    "Computed",
    "Condition",
    "Context",
    "Dbc",
    "Given",
    "Is",
    "Key",
    "MinItems",
    "Multiple",
    "Needs",
    "OneOf",
    "Pattern",
    "Range",
    "Ref",
    "RobotSection",
    "Rule",
    "Table",
    "bound_text",
    "build",
    "check",
    "convert",
    "fail",
    "fraction",
    "got",
    "keys_of",
    "not_negative",
    "number",
    "positive",
    "sections",
    "setting",
    "shown",
    "type_text",
]
