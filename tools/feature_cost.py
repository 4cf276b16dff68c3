"""What SIFT costs a drone photo at each feature size: pycolmap's extraction of two synthetic 12 MP photos
(4000 x 2250, a gravel-like texture at four scales) with `max_image_size` uncapped and at each cap, on the
CPU with the given threads; prints a JSON line per size (seconds a photo, keypoints, the keypoints' largest
x, which stays in the full photo's pixels). `--first-octave 0` runs SIFT without pycolmap's doubling of the
(scaled) photo; SIFT keeps the coarsest levels up to its 8 192 features, so the finest are the first dropped.

    python -m tools.feature_cost --sizes -1 3200 2400 2048 --threads 2 [--first-octave 0]
"""

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def texture(width: int, height: int, seed: int = 0) -> np.ndarray:
    """[H, W, 3] uint8: noise at 2, 8, 32 and 128 px summed (cubic upsampling), stretched to 0-255."""
    import cv2

    rng = np.random.default_rng(seed)
    img = np.zeros((height, width, 3), np.float32)
    for s in (2, 8, 32, 128):
        n = rng.random((height // s + 1, width // s + 1, 3)).astype(np.float32)
        img += cv2.resize(n, (width, height), interpolation=cv2.INTER_CUBIC)
    return (255 * (img - img.min()) / (img.max() - img.min())).astype(np.uint8)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[-1, 3200, 2400, 2048])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--first-octave", type=int, default=-1)
    args = parser.parse_args()

    import cv2
    import pycolmap

    pycolmap.logging.minloglevel = int(pycolmap.logging.Level.ERROR.value)
    with tempfile.TemporaryDirectory() as tmp:
        images = Path(tmp) / "images"
        images.mkdir()
        img = texture(4000, 2250)
        names = [f"{k}.jpg" for k in range(2)]
        for k, name in enumerate(names):
            cv2.imwrite(str(images / name), np.roll(img, 50 * k, axis=1))
        for size in args.sizes:
            db = Path(tmp) / f"{size}.db"
            options = pycolmap.FeatureExtractionOptions()
            options.max_image_size, options.num_threads = size, args.threads
            options.sift.first_octave = args.first_octave
            t0 = time.perf_counter()
            pycolmap.extract_features(db, images, names, extraction_options=options,
                                      device=pycolmap.Device.cpu)
            seconds = (time.perf_counter() - t0) / len(names)
            keypoints = pycolmap.Database.open(str(db)).read_keypoints(1)
            print(json.dumps({"max_image_size": size, "first_octave": args.first_octave,
                              "threads": args.threads, "seconds_a_photo": seconds,
                              "keypoints": len(keypoints), "largest_x": float(keypoints[:, 0].max())}),
                  flush=True)


if __name__ == "__main__":
    main()
