"""The spread of the figures tests/test_survey.py's ground-control test bounds: the synthetic survey written
with each noise seed, then `ragsplat survey` with ground control only (structure from motion included) on
1 and 2 threads (`survey.pipeline.run` with the test's settings); prints a JSON line per run (the median
camera centre and rotation errors, the largest and rms target residual). `--targets-at-feet`: the targets'
heights surveyed as 0, a wrong survey the bounds must fail.

    python -m tools.gcp_spread --seeds 0 1 2 3 4 --threads 1 2
"""

import argparse
import functools
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--targets-at-feet", action="store_true")
    args = parser.parse_args()

    import torch
    from test_survey import write_survey

    from ragsplat.eval.poses import pose_errors
    from ragsplat.survey import pipeline, sfm
    from ragsplat.survey.stages.base import SurveyConfig

    reconstruct = sfm.reconstruct  # the survey's structure from motion, on every core by default
    for seed in args.seeds:
        with tempfile.TemporaryDirectory() as tmp:
            root = write_survey(Path(tmp), seed, args.targets_at_feet)
            for threads in args.threads:
                sfm.reconstruct = functools.partial(reconstruct, threads=threads)
                torch.set_num_threads(threads)
                out = root / f"run{threads}"
                t0 = time.perf_counter()
                # the test's `gcp_args`: ground control only, the level 0, a pinhole, up to the water
                pipeline.run(SurveyConfig(
                    images=root / "images", out=out, gcp=root / "gcp.csv", gcp_pixels=root / "gcp_pixels.csv",
                    water_level=0.0, preset="smoke", lens="pinhole", stop_after="water"))
                water = json.loads((out / "water.json").read_text())
                res = np.array(list(water["gcp_residual_m"].values()))
                poses = pose_errors(out / "model", root / "truth")
                print(json.dumps({"seed": seed, "threads": threads,
                                  "centre_median_m": poses["centre_m"]["median"],
                                  "rotation_median_deg": poses["rotation_deg"]["median"],
                                  "residual_max_m": float(np.abs(res).max()),
                                  "residual_rms_m": float(np.sqrt((res**2).mean())),
                                  "seconds": time.perf_counter() - t0}), flush=True)


if __name__ == "__main__":
    main()
