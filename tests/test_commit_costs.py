"""``scripts/commit_costs.py --paired`` renames a revision's package: every import of ``cfsr``
must name the copy, and nothing else may change (the method is still called ``cfsr``)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "commit_costs.py"


@pytest.fixture(scope="module")
def costs():
    if not SCRIPT.is_file():
        pytest.skip("scripts/ is not in this tree (an installed wheel's test run)")
    spec = importlib.util.spec_from_file_location("commit_costs", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize(
    ("src", "want"),
    [
        ("from cfsr.methods import tfi\n", "from cfsr_x.methods import tfi\n"),
        ("from cfsr import read_dat\n", "from cfsr_x import read_dat\n"),
        ("import cfsr\n", "import cfsr_x\n"),
        ("import cfsr.methods.tfp as tfp\n", "import cfsr_x.methods.tfp as tfp\n"),
        (
            'importlib.import_module("cfsr.methods.cfsr_fine")',
            'importlib.import_module("cfsr_x.methods.cfsr_fine")',
        ),
        ("entry_points(group='cfsr.commands')", "entry_points(group='cfsr_x.commands')"),
        ('register("cfsr", fine)', 'register("cfsr", fine)'),
        ("from cfsr_other import y\n", "from cfsr_other import y\n"),
        ("import cfsrx\n", "import cfsrx\n"),
        ("the cfsr method", "the cfsr method"),
    ],
)
def test_the_renamed_copy_rewrites_imports_only(costs, src, want):
    assert costs.rename_imports(src, "cfsr_x") == want
