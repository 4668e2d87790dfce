"""gpu_floor.py's counts for the forms a GPU runs.

On the CPU the geometry fit takes unfused forms of a few short ops (explicit sums of 2-3 terms,
one gradient component at a time: ``pipeline/optim.py``, ``UNFUSED_DEVICES``), which are faster
there but more ops; ``../shared/tools/gpu_floor.py`` runs on the CPU and so counts those. This
runs the same tool with that set emptied, so it counts the fused forms a CUDA device takes
(both forms give the same bits on the CPU).

    OMP_NUM_THREADS=1 python scripts/gpu_floor_fused.py --B 64,256
"""
import runpy
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TOOL = REPO.parent / "shared" / "tools" / "gpu_floor.py"

if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    from torch_isc.pipeline import optim
    if not TOOL.is_file():
        sys.exit(f"gpu_floor_fused: {TOOL} not found (the tool lives in ../shared/tools)")
    optim.UNFUSED_DEVICES.clear()
    sys.argv = [str(TOOL)] + sys.argv[1:]
    runpy.run_path(str(TOOL), run_name="__main__")
