"""tests/mutations.py stays runnable: each planted bug still edits exactly one place of its file, and each
test it runs still exists (the mutation runs themselves take ~10 minutes: run `python tests/mutations.py`)."""

import os

import pytest

import mutations
from helpers import ROOT


@pytest.mark.parametrize("mutation", mutations.MUTATIONS, ids=lambda m: m.name)
def test_mutation_still_applies(mutation):
    with open(os.path.join(ROOT, mutation.file)) as f:
        assert f.read().count(mutation.old) == 1, f"{mutation.name}: update its text in tests/mutations.py"
    for test in mutation.tests:
        path, _, name = test.partition("::")
        name, _, case = name.partition("[")  # a parametrized test's case: "<script>-<edit>]" or "<script>]"
        with open(os.path.join(ROOT, path)) as f:
            source = f.read()
        assert not name or f"def {name}(" in source, test
        assert not case or f'"{case.rstrip("]").split("-", 1)[-1]}"' in source, test
