"""The world file's schema alone: a built-in example passes it; a wrong type or an unknown key is refused with
the line it stands on (the reader adds the model's own names and units afterwards)."""

from __future__ import annotations

import pytest
from station.mocks.world.example import example_text
from station.mocks.world.worldschema import WorldSchema

from station.strict import check
from station.yamlfile import parse_yaml_doc


class Bad(Exception):
    pass


def test_an_example_world_passes_the_schema():
    doc = parse_yaml_doc(example_text("ur5e"), Bad, "w.yaml")
    assert check(WorldSchema, doc, Bad, "w.yaml") is not None


@pytest.mark.parametrize("edit, field", [(("seed", "abc"), "seed"), (("colour", "red"), "colour")])
def test_a_wrong_value_or_an_unknown_key_names_its_line(edit, field):
    key, value = edit
    text = example_text("ur5e") + f"{key}: {value}\n"
    if key == "seed":
        text = "\n".join(line for line in example_text("ur5e").splitlines() if not line.startswith("seed:"))
        text += "\nseed: abc\n"
    line = text.rstrip("\n").count("\n") + 1  # the edited key is the file's last line
    with pytest.raises(Bad) as e:
        check(WorldSchema, parse_yaml_doc(text, Bad, "w.yaml"), Bad, "w.yaml")
    assert f"w.yaml:{line}:" in str(e.value) and field in str(e.value) and "\n" not in str(e.value)
