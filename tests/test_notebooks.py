"""The notebooks in ``notebooks/``: each one executes top to bottom without an error, and each is stored
without outputs (``python notebooks/strip_outputs.py`` strips them).

A notebook added to the folder is picked up here automatically. Each runs in a fresh ``python3`` kernel of this
interpreter (ipykernel), from the ``notebooks/`` folder, as Jupyter would start it; the kernel inherits this
process's environment, so ``tests/conftest.py``'s ``XLA_FLAGS`` apply to it as well.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
#: seconds any one cell may run (each notebook as a whole is meant to take under 2 minutes on a CPU)
CELL_TIMEOUT = 300


#: notebooks whose execution is left out of the quick tier (``pytest -m "not slow"``; README.md), with the quick
#: tier's tests that check what they show. Whether each is stored without outputs is checked in both tiers.
SLOW = {
    "01_quickstart": "its code is the README's quickstart, test_first_hour.py's snippets, and the loop against "
                     "MuJoCo's <connect> is test_mjcf.py's",
    "02_robots_and_resets": "the robots' resets and rollouts are test_fk_robots.py's and test_robots.py's",
    "04_differentiable_design": "the gradients through the step are test_grad.py's",
    "06_mechanism_design": "the traced design parameters and Hoeken's simulated path are test_design.py's; the "
                           "gradient against finite differences and the optimisation's gain are the notebook's "
                           "own asserts, in the full run",
    "05_training": "brax's PPO learning fourbar_track is checked by its run alone (the bar below); the quick tier "
                   "checks PPO's pieces: test_envs.py's environment API and test_rl_resume.py's training runs",
}

# Notebook 05 trains ``fourbar_track`` with brax's PPO on the Warp backend (Warp's CPU device through the JAX FFI
# inside brax's jit, the backend PPO uses on the GPU): float32, 20 480 environment steps in one epoch of four
# training steps, seed 0, and asserts an improvement of the evaluation return over the initial policy of more than
# 30, to a final return above 50. The eval is the mean return of 64 deterministic episodes of 100 steps (brax's
# ``eval/episode_reward``; 100 is exact tracking at every step). Measured on the 2-core CPU machine at XLA's
# optimisation level 0, the level of the test (tests/conftest.py): the initial policy scores 12.5, 14.4, 12.8, 22.5
# for seeds 0-3, with an episode spread of 17-23, so each eval mean has a standard error of at most 23 / 8 = 2.9; a
# uniformly random policy scores 11.6. After training, seeds 0-3 score 66.8, 64.8, 72.6, 75.1 (and 84.9, 81.6, 77.2,
# 85.4 after twice the steps). 30 is over ten standard errors of the two evals and under two thirds of the smallest
# improvement measured (50.4, seed 1); 50 is over twice the best untrained score and five standard errors under the
# smallest trained one.


def _ids(path: Path) -> str:
    return path.stem


def _executions() -> list:
    return [pytest.param(path, id=path.stem, marks=[pytest.mark.slow] if path.stem in SLOW else [])
            for path in NOTEBOOKS]


def test_there_are_notebooks():
    assert NOTEBOOKS, f"no notebooks found in {NOTEBOOK_DIR}"
    assert set(SLOW) <= {path.stem for path in NOTEBOOKS}, f"SLOW names a notebook that is gone: {sorted(SLOW)}"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=_ids)
def test_notebook_is_stored_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    ran = [i for i, cell in enumerate(nb.cells)
           if cell.cell_type == "code" and (cell.get("outputs") or cell.get("execution_count") is not None)]
    assert not ran, (f"{path.name}: code cells {ran} carry outputs or execution counts; "
                     "run `python notebooks/strip_outputs.py` before committing")
    check = subprocess.run([sys.executable, str(NOTEBOOK_DIR / "strip_outputs.py"), "--check", str(path)],
                           capture_output=True, text=True, check=False)
    assert check.returncode == 0, (f"{path.name} carries run metadata; run `python notebooks/strip_outputs.py` "
                                   f"before committing\n{check.stdout}{check.stderr}")


@pytest.mark.parametrize("path", _executions())
def test_notebook_executes(path):
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipykernel")
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=CELL_TIMEOUT, kernel_name="python3",
                                     resources={"metadata": {"path": str(NOTEBOOK_DIR)}})
    client.execute()  # a cell that raises fails the test with its traceback (nbclient's CellExecutionError)
    errors = [out for cell in nb.cells if cell.cell_type == "code" for out in cell.outputs
              if out.output_type == "error"]
    assert not errors, [f"{e.ename}: {e.evalue}" for e in errors]
