"""The notebooks in ``notebooks/``: each one executes top to bottom without an error, and each is stored
without outputs (``python notebooks/strip_outputs.py`` strips them).

A notebook added to the folder is picked up here automatically. Each runs in a fresh ``python3`` kernel of this
interpreter (ipykernel), from the ``notebooks/`` folder, as Jupyter would start it; the kernel inherits this
process's environment, so ``tests/conftest.py``'s ``XLA_FLAGS`` apply to it as well.
"""

from __future__ import annotations

import copy
import importlib.util
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
#: seconds any one cell may run (each notebook as a whole is meant to take under 2 minutes on a CPU)
CELL_TIMEOUT = 300


#: notebooks whose execution is in the ``slow`` tier (``pytest -m slow``; README.md, under the test command), with
#: the default-tier tests that check what they show. Seconds are their execution in CI at c951ff7
#: (benchmarks/results/s27_cpu/ci_durations_c951ff7.txt). Whether each is stored without outputs is checked in both.
SLOW = {
    "01_quickstart": "36 s; its code is the README's quickstart, test_first_hour.py's snippets, and the loop against "
                     "MuJoCo's <connect> is test_mjcf.py's",
    "02_robots_and_resets": "86 s; the robots' resets and rollouts are test_fk_robots.py's and test_robots.py's",
    "04_differentiable_design": "82 s; the gradients through the step are test_grad.py's",
    "05_training": "199 s; the same PPO run (fourbar_track, 61 440 steps, seed 0) is test_envs_ppo.py's",
}


def _ids(path: Path) -> str:
    return path.stem


def _executions() -> list:
    return [pytest.param(path, id=path.stem, marks=[pytest.mark.slow] if path.stem in SLOW else [])
            for path in NOTEBOOKS]


def _strip_outputs_module():
    spec = importlib.util.spec_from_file_location("strip_outputs", NOTEBOOK_DIR / "strip_outputs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


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
    assert not _strip_outputs_module().strip(copy.deepcopy(nb)), (
        f"{path.name} carries run metadata; run `python notebooks/strip_outputs.py` before committing")


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
