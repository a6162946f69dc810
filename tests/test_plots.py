"""Plots and videos drawn from a synthetic trajectory NPZ (headless, fast)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from sim_backend.plots import load_trajectory, plot_trajectory, write_video


def _synthetic(with_object: bool = True) -> dict:
    """5 robots moving right in a column for 4 s at 10 Hz, robot 2 dies half-way; box of 2 polygons."""
    t = np.arange(40) * 0.1
    n = 5
    pose = np.zeros((len(t), n, 3))
    pose[:, :, 0] = -1.0 + 0.25 * t[:, None]
    pose[:, :, 1] = np.linspace(-0.4, 0.4, n)[None, :] + 0.05 * np.sin(t)[:, None]
    pose[:, :, 2] = 0.2 * np.sin(t)[:, None]
    alive = np.ones((len(t), n), bool)
    alive[20:, 2] = False
    traj = {
        "t": t,
        "robot_pose": pose,
        "robot_alive": alive,
        "path": np.array([[0.0, 0.0, 0.0], [0.5, 0.3, 45.0], [1.0, 0.3, 90.0]]),
        "robot_radius": np.array(0.07),
        "arena_walls": np.array([-1.5, -1.0, 1.5, 1.0]),
        "centroid_estimate": np.column_stack([0.2 * t - 0.3, np.full(len(t), 0.05)]),
    }
    if with_object:
        half = np.array([[-0.2, -0.1], [0.2, -0.1], [0.2, 0.1], [-0.2, 0.1]])
        nub = np.array([[0.2, -0.05], [0.3, -0.05], [0.3, 0.05], [0.2, 0.05]])
        traj["object_outline"] = np.concatenate([half, nub])
        traj["object_outline_index"] = np.array([0, 4, 8])
        traj["object_pose"] = np.column_stack([-0.3 + 0.2 * t, np.zeros(len(t)), 0.1 * t])
    else:
        traj["arena_walls"] = np.full(4, np.nan)
        traj["path"] = np.zeros((0, 3))
        del traj["centroid_estimate"]
    return traj


def _saved(tmp_path: Path, with_object: bool = True) -> dict:
    npz = tmp_path / "traj.npz"
    np.savez(npz, **_synthetic(with_object))
    return load_trajectory(npz)


def _assert_picture(png: Path) -> None:
    assert png.exists() and png.stat().st_size > 0
    img = np.asarray(Image.open(png).convert("RGB"))
    assert img.ndim == 3 and len(np.unique(img.reshape(-1, 3), axis=0)) > 1


def test_load_trajectory_round_trip(tmp_path: Path) -> None:
    traj = _saved(tmp_path)
    assert traj["robot_pose"].shape == (40, 5, 3)
    assert traj["robot_alive"].dtype == bool
    assert traj["robot_radius"].shape == ()


def test_plot_trajectory_writes_png(tmp_path: Path) -> None:
    png = tmp_path / "run.png"
    plot_trajectory(_saved(tmp_path), png, title="synthetic")
    _assert_picture(png)


def test_plot_without_object(tmp_path: Path) -> None:
    png = tmp_path / "no_object.png"
    plot_trajectory(_saved(tmp_path, with_object=False), png)
    _assert_picture(png)


def test_write_video_gif(tmp_path: Path) -> None:
    gif = tmp_path / "run.gif"
    write_video(_saved(tmp_path), gif, fps=5, max_frames=4, title="synthetic")
    assert gif.stat().st_size > 0
    with Image.open(gif) as img:
        assert img.n_frames > 1


def test_write_video_without_object(tmp_path: Path) -> None:
    gif = tmp_path / "no_object.gif"
    write_video(_saved(tmp_path, with_object=False), gif, max_frames=3)
    with Image.open(gif) as img:
        assert img.n_frames > 1


def test_unsupported_suffix(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"\.avi"):
        write_video(_saved(tmp_path), tmp_path / "run.avi", max_frames=2)


def _no_samples() -> dict:
    """A run whose behaviour raised at its first step (t = 0): every per-sample array is empty."""
    traj = _synthetic()
    for key in ("t", "robot_pose", "robot_alive", "object_pose", "centroid_estimate"):
        traj[key] = traj[key][:0]
    return traj


def test_a_run_without_samples_is_drawn_as_its_arena_with_a_note(tmp_path: Path) -> None:
    """Plotting it raised IndexError in khepri's own code, hiding the behaviour's crash report."""
    png, gif = tmp_path / "empty.png", tmp_path / "empty.gif"
    plot_trajectory(_no_samples(), png, title="crashed at t = 0")
    _assert_picture(png)
    write_video(_no_samples(), gif)
    with Image.open(gif) as img:
        assert img.n_frames == 1
