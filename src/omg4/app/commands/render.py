"""``omg4 render --model M (--data DATA | --camera CAM.json) --time T --out PNG|NPY|MP4 [--path orbit|spiral|dataset]``
or ``omg4 render --model M --path camera_path.json --out MP4``.

An ``.mp4`` plays the model's time range from one camera, or, with ``--path``, from a camera
that moves along a path around the reference cameras while time advances (a free-viewpoint
video; :mod:`omg4.render.paths`), or along the cameras of a nerfstudio camera path file
(:mod:`omg4.io.camera_path`). ``--width``/``--height`` set the image size of any of them.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from omg4.app.commands.common import (add_background_argument, add_device_arguments, add_force_argument, add_scene_arguments,
                                  background_from_args, device_from_args, finite_float, float_in, int_at_least)
from omg4.render.paths import PATHS


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", required=True, type=Path, help="checkpoint (.safetensors) or compressed .omg4 file")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--data", type=Path, help="dataset folder: render one of its cameras")
    src.add_argument("--camera", type=Path, help='CAM.json: {"K": 3x3, "viewmat": 4x4, "width": W, "height": H}')
    add_scene_arguments(p, positional=False)
    p.add_argument("--camera-name", help="with --data: which camera (default: the first test camera)")
    p.add_argument("--time", type=finite_float,
                   help="timestamp for an image, inside the model's time range (default: its start)")
    p.add_argument("--out", required=True, type=Path, help=".png or .npy (float32 [H,W,3]) image, or .mp4 video "
                                                           "over the whole time range")
    p.add_argument("--num-frames", type=int_at_least(1),
                   help="frames of an .mp4 (default: the dataset's frame count, or 60)")
    p.add_argument("--fps", type=float_in(0.0, 1000.0),
                   help="frame rate of an .mp4, in (0, 1000] (default: a camera path file's, else 30)")
    p.add_argument("--path", type=camera_path_source, metavar="{" + ",".join(PATHS) + "} or FILE.json",
                   help="free-viewpoint .mp4: the camera moves while time advances — orbit (a circle that frames the "
                        "scene: around it for cameras on every side, around the cameras for a forward-facing rig), "
                        "spiral (forward-facing, around the cameras), dataset (through the dataset's cameras), with "
                        "reference cameras from --data or the one --camera; or a nerfstudio camera_path.json in the "
                        "model's normalized world (its cameras, sizes, frame rate and render times)")
    p.add_argument("--width", type=int_at_least(1), help="image width in pixels (default: the camera's; alone, "
                                                          "the height follows the camera's aspect ratio)")
    p.add_argument("--height", type=int_at_least(1), help="image height in pixels (default: the camera's; alone, "
                                                           "the width follows the camera's aspect ratio)")
    p.add_argument("--time-range", metavar="A:B", help="clip of an .mp4: times from A to B (default: the model's range)")
    add_background_argument(p)
    add_device_arguments(p)
    add_force_argument(p)


def camera_path_source(text: str) -> str:
    """An argparse type: a path name of :data:`~omg4.render.paths.PATHS`, or a ``.json`` camera path file."""
    if text in PATHS or text.lower().endswith(".json"):
        return text
    raise argparse.ArgumentTypeError(f"expected one of {', '.join(PATHS)} or a camera_path.json file, got '{text}'")


def _sized(camera, width: int | None, height: int | None):
    """``camera`` at ``--width``/``--height`` (one of them alone keeps its aspect ratio)."""
    if width is None and height is None:
        return camera
    if width is None:
        width = max(1, round(camera.width * height / camera.height))
    if height is None:
        height = max(1, round(camera.height * width / camera.width))
    return camera.resized(width, height)


def _cameras(args):
    """(the camera to render, the reference cameras of a path, the scene or None)."""
    from omg4.app.commands.common import load_scene_from_args
    from omg4.data.scene import Camera
    from omg4.errors import OMG4Error

    if args.camera is None and args.data is None:  # a camera path file gives every camera
        return None, [], None
    if args.camera is not None:
        try:
            camera = Camera.from_json(json.loads(args.camera.read_text())).check_renderable()
        except FileNotFoundError:
            raise OMG4Error(f"camera file {args.camera} does not exist") from None
        except (OSError, UnicodeDecodeError) as e:
            raise OMG4Error(f"cannot read the camera file {args.camera} ({getattr(e, 'strerror', None) or e})") from None
        except (ValueError, KeyError, TypeError) as e:
            raise OMG4Error(f"{args.camera}: not a camera JSON ({type(e).__name__}: {e})") from None
        return camera, [camera], None
    scene = load_scene_from_args(args)
    cams = scene.cameras()
    if args.camera_name:
        cams = [c for c in cams if c.name == args.camera_name]
        if not cams:
            raise OMG4Error(f"no camera named '{args.camera_name}' in {args.data}")
    references = scene.train_cameras() if args.path == "dataset" else scene.cameras()
    return cams[0].check_renderable(), references, scene


def _time_range(text: str | None, model_range: tuple[float, float]) -> tuple[float, float]:
    from omg4.errors import OMG4Error

    t0, t1 = model_range
    if not text:
        return t0, t1
    try:
        a, b = (float(x) for x in text.split(":"))
    except ValueError:
        raise OMG4Error(f"--time-range expects A:B, got '{text}'") from None
    if not (t0 <= a < b <= t1):
        raise OMG4Error(f"--time-range {text} must satisfy {t0:g} <= A < B <= {t1:g} (the model's time range)")
    return a, b


def run(args) -> int:
    import numpy as np
    import torch

    from omg4.app.outputs import check_outputs
    from omg4.errors import OMG4Error
    from omg4.io.images import save_npy, save_png
    from omg4.io.video import write_video
    from omg4.models import load_model
    from omg4.render.view import render_view

    args.fps_given = args.fps is not None
    args.fps = args.fps if args.fps_given else 30.0
    suffix = args.out.suffix.lower()
    if suffix not in (".png", ".npy", ".mp4"):
        raise OMG4Error(f"--out must end in .png, .npy or .mp4, got '{args.out.name}'")
    path_file = Path(args.path) if args.path and args.path not in PATHS else None
    if args.data is None and args.camera is None and (path_file is None or suffix != ".mp4"):
        raise OMG4Error("give the camera: --data DATA or --camera CAM.json (or, for an .mp4, --path camera_path.json)")
    check_outputs({"--out": args.out}, inputs=[args.model, args.data, args.camera, path_file], datasets=[args.data],
                  force=args.force)
    device = device_from_args(args)
    model = load_model(args.model, device)
    t0, t1 = model.config.time_range
    if args.time is not None and not t0 <= args.time <= t1:
        raise OMG4Error(f"--time {args.time:g} lies outside the model's time range [{t0:g}, {t1:g}]")
    if suffix != ".mp4" and (args.path or args.time_range):
        raise OMG4Error("--path and --time-range make videos: give an --out ending in .mp4")
    start, end = _time_range(args.time_range, (t0, t1))
    camera, references, scene = _cameras(args)
    bg = torch.tensor(background_from_args(args), device=device)

    def frame(cam, t: float) -> np.ndarray:
        with torch.no_grad():
            rendered, _ = render_view(model, cam, t, background=bg, backend=args.backend, device=device)
        return rendered.image.clamp(0, 1).cpu().numpy()

    if suffix == ".mp4":
        from tqdm.auto import tqdm

        from omg4.render.paths import camera_path

        fps = args.fps
        if args.path and args.path not in PATHS:  # a camera_path.json: its cameras, times and frame rate
            from omg4.io.camera_path import read_camera_path

            if args.num_frames:
                raise OMG4Error("--num-frames applies to the built-in paths; a camera path file has its own frames")
            read = read_camera_path(args.path)
            cameras, n = read.cameras, len(read.cameras)
            fractions = read.times or [i / n for i in range(n)]
            times = [start + (end - start) * f for f in fractions]
            fps = args.fps if args.fps_given else (read.fps or args.fps)
        else:
            n = args.num_frames or (scene.num_frames if scene is not None and scene.num_frames else 60)
            times = [start + (end - start) * i / n for i in range(n)]
            cameras = camera_path(args.path, references, n) if args.path else [camera] * n
        cameras = [_sized(c, args.width, args.height) for c in cameras]
        frames = (frame(c, t) for c, t in tqdm(list(zip(cameras, times)), desc="render"))
        count = write_video(args.out, frames, fps=fps)
        what = f"{args.path} path" if args.path else f"camera {camera.name or 'custom'}"
        print(f"wrote {args.out} ({count} frames, {cameras[0].width}x{cameras[0].height}, {what}, t {start:g} to "
              f"{end:g})")
        return 0
    t = t0 if args.time is None else args.time
    camera = _sized(camera, args.width, args.height)
    img = frame(camera, t)
    (save_png if suffix == ".png" else save_npy)(args.out, img)
    print(f"wrote {args.out} ({camera.width}x{camera.height}, camera {camera.name or 'custom'}, t={t:g})")
    return 0
