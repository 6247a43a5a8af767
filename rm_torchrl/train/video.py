"""Videos of a policy's episodes, rendered offscreen by MuJoCo, each frame showing the RM state.

Every frame carries a strip with the step, the return so far, the RM state (the events in the
order they occurred) and how many of the spec's events were reached. ``.gif`` is written with
Pillow, ``.mp4`` with imageio's ffmpeg (``pip install 'rm_torchrl[video]'``); on a machine without
a display, set ``MUJOCO_GL=egl`` (or ``osmesa``). Files are written to a temporary name and renamed
when complete.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from rm_torchrl.errors import RMError
from rm_torchrl.progress import progress_bar

FORMATS = (".gif", ".mp4")
STRIP = 44  # pixel rows of the caption strip above each frame


def caption(frame: np.ndarray, lines: list[str]) -> np.ndarray:
    """``frame`` (H, W, 3 uint8) with a dark strip of text lines on top."""
    from PIL import Image, ImageDraw

    h, w, _ = frame.shape
    canvas = Image.new("RGB", (w, h + STRIP), (20, 20, 28))
    canvas.paste(Image.fromarray(frame), (0, STRIP))
    draw = ImageDraw.Draw(canvas)
    for i, line in enumerate(lines[:3]):
        draw.text((6, 3 + 13 * i), line, fill=(235, 235, 235))
    return np.asarray(canvas)


def rm_caption(state: torch.Tensor, names: list[str]) -> tuple[str, str]:
    """("RM: e0 > reach_handle > door_0.2", "events 2/4") for slot state ``state`` over the spec's ``names``."""
    order = [names[int(s) - 1] for s in state.tolist() if s > 0]
    return "RM: " + " > ".join(["e0", *order]), f"events {len(order)}/{len(names)}"


def render_episodes(env, policy, episodes: int, max_steps: int, event_names: list[str] | None,
                    seed: int = 0, desc: str = "video") -> list[np.ndarray]:
    """Captioned frames of ``episodes`` deterministic episodes of ``policy`` in ``env`` (which renders rgb arrays).

    A progress bar of the frames goes to stderr (whole lines when it is not a terminal).
    """
    frames = []
    env.set_seed(seed)
    per_episode = max_steps + 1
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC), \
            progress_bar(total=episodes * per_episode, desc=desc, unit="frame", leave=False) as bar:
        for episode in range(episodes):
            td, total, done = env.reset(), 0.0, False
            for step in range(per_episode):
                lines = [f"episode {episode + 1}/{episodes}  step {step}  return {total:.1f}" + ("  (done)" if done else "")]
                if event_names and "rm_state" in td.keys():
                    lines += list(rm_caption(td["rm_state"].cpu(), event_names))
                frames.append(caption(np.asarray(env.base_env.render()), lines))
                bar.update()
                if done or step == max_steps:
                    break
                td = env.step(policy(td))
                total += float(td["next", "reward"].sum())
                done = bool(td["next", "done"].any())
                td = step_mdp(td)
            bar.total -= per_episode - (step + 1)  # an episode that ended early has fewer frames
    return frames


def check_video_path(path) -> Path:
    """``path`` if a video can be written there (a known suffix, an existing directory), else a one-line RMError."""
    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise RMError(f"--video must end in {' or '.join(FORMATS)}, got {path.name!r}")
    if not path.parent.is_dir():
        raise RMError(f"cannot write {path}: {path.parent} is not a directory")
    if path.is_dir():
        raise RMError(f"cannot write {path}: it is a directory")
    try:  # a read-only folder is found now, not after the evaluation
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", suffix=".probe"):
            pass
    except OSError as err:
        raise RMError(f"cannot write {path}: {err.strerror}") from None
    return path


def write_video(frames: list[np.ndarray], path, fps: int = 20) -> Path:
    """``frames`` as ``path`` (.gif or .mp4), through a temporary file renamed when complete."""
    path = check_video_path(path)
    if not frames:
        raise RMError("no frames to write")
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp{path.suffix}")
    try:
        if path.suffix.lower() == ".gif":
            from PIL import Image

            images = [Image.fromarray(f) for f in frames]
            images[0].save(tmp, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
        else:
            try:
                import imageio.v2 as imageio
                import imageio_ffmpeg  # noqa: F401  (the mp4 writer's ffmpeg)
            except ImportError as err:
                raise RMError(f"mp4 videos need imageio and its ffmpeg: pip install 'rm_torchrl[video]' ({err})") from None
            imageio.mimwrite(tmp, frames, fps=fps, macro_block_size=1)
        os.replace(tmp, path)
    except OSError as err:
        raise RMError(f"cannot write {path}: {err.strerror or err}") from None
    finally:
        tmp.unlink(missing_ok=True)
    return path
