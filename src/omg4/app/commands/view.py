"""``omg4 view MODEL [--data DATA] [--port P] [--device ...]``: the interactive browser viewer (:mod:`omg4.app.viewer`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from omg4.app.commands.common import add_background_argument, add_device_arguments, add_scene_arguments, int_in
from omg4.data.scene import MAX_IMAGE_SIDE


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", type=Path, help="checkpoint (.safetensors) or compressed .omg4 file")
    p.add_argument("--data", type=Path, help="dataset folder: its cameras become the camera presets "
                                             "(default: an orbit around the model)")
    add_scene_arguments(p, positional=False)
    p.add_argument("--port", type=int_in(1, 65535), default=8080, help="port to serve on (default 8080)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1; 0.0.0.0 to reach it from other machines)")
    p.add_argument("--resolution", type=int_in(16, MAX_IMAGE_SIDE), default=640,
                   help="long side in pixels of a still frame (half of it while the camera moves or the clip plays)")
    add_background_argument(p)
    add_device_arguments(p)


def run(args) -> int:
    import torch
    import viser  # noqa: F401  (the viewer extra: where it is missing, a one-line error with its pip command)

    from omg4.app.commands.common import background_from_args, device_from_args, load_scene_from_args
    from omg4.app.viewer import Viewer, ViewerSettings, check_port_free, view_presets
    from omg4.models import load_model

    check_port_free(args.host, args.port)  # before the model loads: a busy port fails at once
    device = device_from_args(args)
    model = load_model(args.model, device)
    cameras = load_scene_from_args(args, decode=False).cameras() if args.data is not None else None
    settings = ViewerSettings(host=args.host, port=args.port, long_side=args.resolution,
                              moving_long_side=max(16, args.resolution // 2), backend=args.backend, device=str(device))
    file_bytes = getattr(model, "storage_bytes", None) or args.model.stat().st_size  # a sequence or run: all of it
    viewer = Viewer(model, view_presets(model, cameras), file_bytes=file_bytes, settings=settings)
    viewer.background = torch.tensor(background_from_args(args), device=device)
    host = "localhost" if args.host in ("127.0.0.1", "0.0.0.0") else args.host
    print(f"omg4 view: http://{host}:{viewer.server.get_port()} ({model.num_gaussians:,} Gaussians; Ctrl-C to stop)")
    try:
        viewer.server.sleep_forever()
    except KeyboardInterrupt:
        viewer.stop()
    return 0
