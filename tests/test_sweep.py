"""The Hydra multirun grid search with the joblib launcher writes one table of all runs."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.conftest import ROOT
from tests.test_training import TINY


@pytest.mark.slow
def test_grid_sweep_runs_in_parallel_and_writes_a_table(tmp_path):
    cmd = [
        sys.executable, "-m", "pinnmpc.train", "-m", "hparams_search=grid", *TINY, "trainer.max_epochs=2",
        "hydra.sweeper.params={model.ic:'hard,soft'}", f"hydra.sweep.dir={tmp_path}",
    ]  # fmt: skip
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    table = (tmp_path / "sweep_results.md").read_text()
    assert "model.ic=hard" in table and "model.ic=soft" in table
    csv_rows = (tmp_path / "sweep_results.csv").read_text().strip().splitlines()
    assert len(csv_rows) == 1 + 2 * 2  # header + model.ic x module.residual_form (TINY fixes n_collocation)
