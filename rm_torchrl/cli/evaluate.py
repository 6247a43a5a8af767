"""``rmrl evaluate RUN_DIR``: the trainer's evaluation of a run's checkpoint (finished or interrupted).

With ``--video`` the renderer is made (and one frame drawn) before the evaluation, so a machine
without an OpenGL backend for MuJoCo is refused in one line before any episode runs; if the video
still fails afterwards, the figures are printed first and the failure is one line.
"""
from __future__ import annotations

import json
import math
import sys


HELP = "evaluate a run's checkpoint in its env, as the trainer does"


def add_arguments(p) -> None:
    p.add_argument("run_dir", help="a run directory (recipe.yaml and checkpoint.pt)")
    p.add_argument("--episodes", type=int, help="episodes (default: the recipe's eval.episodes)")
    p.add_argument("--seed", type=int, help="environment seed, 0..2**32-1 (default: the run's seed)")
    p.add_argument("--device", default="cpu", help="where the policy runs: cpu (default), cuda, cuda:N, auto")
    p.add_argument("--sequential", action="store_true",
                   help="run the episodes one after another in one env (default: as one batch of envs; same starts)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a line of figures")
    p.add_argument("--video", metavar="FILE", help="also render episodes to FILE (.mp4 or .gif) with the RM state "
                                                 "drawn on each frame (MUJOCO_GL=egl without a display)")
    p.add_argument("--video-episodes", type=int, default=1, help="episodes in the video (default 1)")


def figures(result: dict) -> str:
    """The line of figures; a spread only over two or more episodes, RM figures only when the RM is tracked."""
    spread = f" ± {result['return_std']:.1f}" if result["episodes"] > 1 else ""
    parts = [f"return {result['return_mean']:.1f}{spread} ({result['reward']} reward)", f"score {result['score']:.1f}"]
    if math.isfinite(result["success_rate"]):  # nan without an event spec
        parts += [f"success {result['success_rate']:.2f}", f"events {result['events_mean']:.2f}"]
    episodes = result["episodes"]
    return f"{', '.join(parts)} over {episodes} episode{'s' * (episodes != 1)}"


def run(args) -> int:
    from rm_torchrl.errors import RMError
    from rm_torchrl.train.config import check_seed
    from rm_torchrl.train.policy import load_policy
    from rm_torchrl.train.video import check_video_path

    if args.episodes is not None and args.episodes < 1:
        raise RMError(f"--episodes must be positive, got {args.episodes}")
    if args.seed is not None:
        check_seed(args.seed, "--seed")
    if args.video:
        check_video_path(args.video)
        if args.video_episodes < 1:
            raise RMError(f"--video-episodes must be positive, got {args.video_episodes}")
    loaded = load_policy(args.run_dir, device=args.device)
    renderer = loaded.render_env() if args.video else None  # before the evaluation: no GL is one line now
    video_error = None
    try:
        evaluation = loaded.evaluate(args.episodes, args.seed, vectorised=not args.sequential)
        result = {"run": str(args.run_dir), "step": loaded.step, **evaluation}
        if renderer is not None:
            try:
                result["video"] = str(loaded.video(args.video, episodes=args.video_episodes, seed=args.seed,
                                                   env=renderer))
            except Exception as err:  # the figures above are kept whatever the renderer does
                video_error = err if isinstance(err, RMError) else f"{type(err).__name__}: {' '.join(str(err).split())}"
    finally:
        if renderer is not None:
            renderer.close()
    if args.json:
        print(json.dumps(result))
    else:
        print(f"{args.run_dir} at step {result['step']}: {figures(result)}"
              + (f"; video: {result['video']}" if "video" in result else ""))
    if video_error is not None:
        sys.stdout.flush()
        raise RMError(f"the evaluation above is complete, but the video {args.video} failed: {video_error}")
    return 0
