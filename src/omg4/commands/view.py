"""``omg4 view MODEL [--data DATA] [--port P] [--device ...]``: the interactive browser viewer (:mod:`omg4.viewer`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from omg4.commands.common import add_background_argument, add_device_arguments, int_at_least


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", type=Path, help="checkpoint (.safetensors) or compressed .omg4 file")
    p.add_argument("--data", type=Path, help="dataset folder: its cameras become the camera presets "
                                             "(default: an orbit around the model)")
    p.add_argument("--port", type=int_at_least(1), default=8080, help="port to serve on (default 8080)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1; 0.0.0.0 to reach it from other machines)")
    p.add_argument("--resolution", type=int_at_least(16), default=640,
                   help="long side in pixels of a still frame (half of it while the camera moves)")
    add_background_argument(p)
    add_device_arguments(p)


def run(args) -> int:
    import torch

    from omg4.commands.common import background_from_args, device_from_args
    from omg4.evaluate import load_model
    from omg4.viewer import Viewer, ViewerSettings, check_port_free, view_presets

    check_port_free(args.host, args.port)  # before the model loads: a busy port fails at once
    device = device_from_args(args)
    model = load_model(args.model, device)
    cameras = None
    if args.data is not None:
        from omg4.data import load_scene

        scene = load_scene(args.data, decode=False, progress=False)
        cameras = scene.test_cameras() + scene.train_cameras()
    settings = ViewerSettings(host=args.host, port=args.port, long_side=args.resolution,
                              moving_long_side=max(16, args.resolution // 2), backend=args.backend, device=str(device))
    viewer = Viewer(model, view_presets(model, cameras), file_bytes=args.model.stat().st_size, settings=settings)
    viewer.background = torch.tensor(background_from_args(args), device=device)
    print(f"omg4 view: http://{'localhost' if args.host in ('127.0.0.1', '0.0.0.0') else args.host}:{args.port} "
          f"({model.num_gaussians:,} Gaussians; Ctrl-C to stop)")
    try:
        while True:
            viewer.server.sleep_forever()
    except KeyboardInterrupt:
        viewer.stop()
        return 0
