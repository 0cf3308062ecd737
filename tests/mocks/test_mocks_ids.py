"""``station.mocks.ids``: device id lists as mock commands and world files write them."""

import pytest
from station.mocks.ids import parse_id_list


def test_ranges_lists_and_sequences():
    assert parse_id_list("11-14") == [11, 12, 13, 14]
    assert parse_id_list("1, 3,5-6") == [1, 3, 5, 6]
    assert parse_id_list([11, "12"]) == [11, 12]
    assert parse_id_list("7") == [7]


@pytest.mark.parametrize("bad", ["14-11", "a-b", "1,x"])
def test_bad_lists_raise(bad):
    with pytest.raises(ValueError):
        parse_id_list(bad)
