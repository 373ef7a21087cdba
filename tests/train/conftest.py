"""Fixtures of the training tests."""

import pytest
from fixtures.toy_data import write_toy_records


@pytest.fixture(scope="session")
def toy(tmp_path_factory):
    """A toy records folder (tests/fixtures/toy_data.py): 16 train and 6 val records."""
    return write_toy_records(tmp_path_factory.mktemp("toy"), num_train=16, num_val=6,
                             num_templates=24)
