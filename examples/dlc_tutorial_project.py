"""Write the synthetic DeepLabCut project of ``docs/tutorial.md``.

A rat (the ACM rat model with an individual's bone lengths) filmed by four cameras at 100 Hz, as
DeepLabCut leaves the project after labelling, training, ``analyze_videos`` and
``filterpredictions``; plus one calibration video per camera of a ChArUco board (10 x 7 squares
of 2.5 cm, 4x4 ArUco markers: acm-rs's default board)::

    python examples/dlc_tutorial_project.py OUT [--frames 300] [--seed 0]

    OUT/rat-Alice-2024-01-15/
      config.yaml                                  DeepLabCut's project config
      videos/s1-cam0.mp4 ...                       the recordings
      videos/s1-cam0DLC_resnet50_ratJan15shuffle1_100000.h5|.csv   predictions (+ _filtered)
      labeled-data/s1-cam0/CollectedData_Alice.h5|.csv, img*.png   manual labels
      calibration/calib-cam0.avi ...               board videos (acm-rs reads this folder)
    OUT/truth.npz                                  true joints, skeleton lengths (for checking)

Everything is computed from the model: nothing here is real data.
"""

from __future__ import annotations

import argparse
import pickle
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import yaml
from scipy.signal import medfilt

import acm_rs
from acm_rs import datasets, models
from acm_rs.calibration import BoardSpec
from acm_rs.demo import look_at
from acm_rs.rotation import rodrigues

FPS = 100.0
SIZE = (1280, 1024)
SCORER = "Alice"
NET = "DLC_resnet50_ratJan15shuffle1_100000"


def tutorial_rig() -> acm_rs.CameraRig:
    """Four cameras on a ring 60 cm from the arena centre, 45 cm up (cm, z up), no distortion."""
    cams = []
    for i in range(4):
        a = np.pi / 4 + i * np.pi / 2
        center = np.array([60 * np.cos(a), 60 * np.sin(a), 45.0])
        rvec, tvec = look_at(center, np.array([0.0, 0.0, 3.0]), np.array([0.0, 0.0, 1.0]))
        k = np.array([[1400.0, 0, 640], [0, 1400.0, 512], [0, 0, 1]])
        cams.append(acm_rs.Camera(k, [0.0, 0.0], rvec, tvec, SIZE, f"cam{i}"))
    return acm_rs.CameraRig(cams, units="cm")


def board_videos(rig, folder: Path, n_views: int, rng) -> None:
    spec = BoardSpec.from_dict(
        {"board_type": "charuco", "board_size": [10, 7], "board_square_side_length": 2.5,
         "board_marker_length": 1.875, "board_marker_bits": 4, "board_marker_dict_number": 50}
    )  # fmt: skip
    img, to_px = spec.render(80, 40)
    centre = spec.board_points.mean(axis=0)
    writers = [
        cv2.VideoWriter(str(folder / f"calib-{c.name}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10.0,
                        SIZE, isColor=False)
        for c in rig
    ]  # fmt: skip
    for _ in range(n_views):
        # the board lies face up (its z axis points down, away from the cameras), tilted and
        # moved around the arena
        tilt = rodrigues(rng.normal(0, 0.3, 3) * [1, 1, 2])
        rb = tilt @ np.diag([1.0, -1.0, -1.0])
        tb = rng.uniform([-12, -12, 0], [12, 12, 12]) - rb @ centre
        for cam, out in zip(rig, writers, strict=True):
            rc = cam.rotation_matrix @ rb
            tc = cam.rotation_matrix @ tb + cam.tvec
            hom = cam.matrix @ np.column_stack([rc[:, 0], rc[:, 1], tc])
            frame = cv2.warpPerspective(img, hom @ np.linalg.inv(to_px), SIZE, borderValue=90)
            noisy = np.clip(frame + rng.normal(0, 2.0, frame.shape), 0, 255).astype(np.uint8)
            out.write(noisy)
    for out in writers:
        out.release()


def render(points: np.ndarray) -> np.ndarray:
    """A dark frame with the markers drawn (what a camera of the recording 'sees')."""
    frame = np.full((SIZE[1], SIZE[0], 3), 35, np.uint8)
    for x, y in points:
        if np.isfinite(x) and np.isfinite(y):
            cv2.circle(frame, (int(round(x)), int(round(y))), 4, (230, 230, 230), -1)
    return frame


def dlc_frame(det: np.ndarray, lik: np.ndarray, bodyparts, index=None) -> pd.DataFrame:
    """DeepLabCut's DataFrame: columns (scorer, bodyparts, coords)."""
    coords = ["x", "y"] if lik is None else ["x", "y", "likelihood"]
    cols = pd.MultiIndex.from_product(
        [[NET if lik is not None else SCORER], bodyparts, coords],
        names=["scorer", "bodyparts", "coords"],
    )
    data = det if lik is None else np.concatenate([det, lik[..., None]], axis=-1)
    return pd.DataFrame(data.reshape(len(data), -1), columns=cols, index=index)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", help="folder to create the project in")
    ap.add_argument("--frames", type=int, default=300, help="frames of the recording (300)")
    ap.add_argument("--seed", type=int, default=0, help="seed (0)")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    root = Path(args.out) / "rat-Alice-2024-01-15"
    for sub in ("videos", "labeled-data", "calibration"):
        (root / sub).mkdir(parents=True, exist_ok=False)
    rig = tutorial_rig()
    rat = models.rat()
    animal = datasets.individual_skeleton(rat, seed=args.seed + 1)
    bodyparts = list(rat.marker_names)
    t, r = datasets.smooth_motion(animal, args.frames, seed=args.seed + 2)
    det, lik = datasets.dlc_like_detections(rig, animal, t, r, seed=args.seed + 3)
    clean = animal.project(rig, t, r)  # (C, T, M, 2)

    doc = {
        "Task": "rat", "scorer": SCORER, "date": "Jan15", "multianimalproject": False,
        "identity": None, "project_path": str(root.resolve()),
        "video_sets": {str((root / "videos" / f"s1-{c.name}.mp4").resolve()):
                       {"crop": f"0, {SIZE[0]}, 0, {SIZE[1]}"} for c in rig},
        "bodyparts": bodyparts, "start": 0, "stop": 1, "numframes2pick": 20,
        "skeleton": [], "skeleton_color": "black", "pcutoff": 0.6, "dotsize": 6,
        "alphavalue": 0.7, "colormap": "rainbow", "TrainingFraction": [0.95], "iteration": 0,
        "default_net_type": "resnet_50", "default_augmenter": "default", "snapshotindex": -1,
        "batch_size": 8, "cropping": False, "x1": 0, "x2": 640, "y1": 277, "y2": 624,
        "corner2move2": [50, 50], "move2corner": True,
    }  # fmt: skip
    (root / "config.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))

    labelled = np.sort(rng.choice(args.frames, 40, replace=False))
    for c, cam in enumerate(rig):
        stem = f"s1-{cam.name}"
        video = cv2.VideoWriter(str(root / "videos" / f"{stem}.mp4"),
                                cv2.VideoWriter_fourcc(*"mp4v"), FPS, SIZE)  # fmt: skip
        frames = [render(clean[c, f]) for f in range(args.frames)]
        for frame in frames:
            video.write(frame)
        video.release()
        # analyze_videos: .h5 (PyTables, key df_with_missing) and .csv
        df = dlc_frame(det[c], lik[c], bodyparts)
        base = root / "videos" / f"{stem}{NET}"
        df.to_hdf(f"{base}.h5", key="df_with_missing", format="table", mode="w")
        df.to_csv(f"{base}.csv")
        with open(f"{base}_meta.pickle", "wb") as fh:
            pickle.dump({"data": {"nframes": args.frames, "fps": FPS, "Scorer": NET}}, fh)
        # filterpredictions (median, window 5): the same analysis, smoothed
        filt = df.copy()
        for col in filt.columns:
            if col[2] in ("x", "y"):
                filt[col] = medfilt(np.nan_to_num(filt[col].to_numpy(), nan=0.0), 5)
        filt.to_hdf(f"{base}_filtered.h5", key="df_with_missing", format="table", mode="w")
        filt.to_csv(f"{base}_filtered.csv")
        # labelling: frames extracted as PNG, labels with 1 px error, some parts not labelled
        sub = root / "labeled-data" / stem
        sub.mkdir()
        pts = clean[c, labelled] + rng.normal(0, 1.0, clean[c, labelled].shape)
        pts[rng.random(pts.shape[:2]) < 0.1] = np.nan
        index = pd.MultiIndex.from_tuples(
            [("labeled-data", stem, f"img{f:04d}.png") for f in labelled]
        )
        lab = dlc_frame(pts, None, bodyparts, index=index)
        lab.to_hdf(sub / f"CollectedData_{SCORER}.h5", key="keypoints", mode="w")
        lab.to_csv(sub / f"CollectedData_{SCORER}.csv")
        for f in labelled:
            cv2.imwrite(str(sub / f"img{f:04d}.png"), frames[f])
    board_videos(rig, root / "calibration", 50, rng)
    joints = animal.forward(t, r)[0]
    np.savez(Path(args.out) / "truth.npz", joints=joints, bone_lengths=animal.bone_lengths,
             bone_names=np.array(animal.bone_names), rig=rig.get_params())  # fmt: skip
    n = sum(1 for p in root.rglob("*") if p.is_file())
    print(f"wrote {root} ({n} files) and {Path(args.out) / 'truth.npz'}")


if __name__ == "__main__":
    main()
