"""Argument groups shared by several subcommands."""

from __future__ import annotations

import argparse
import json
import math
import sys
import unicodedata
from pathlib import Path


def int_at_least(low: int, high: int | None = None):
    """An argparse type: an integer ≥ ``low`` (and ≤ ``high`` when given)."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got '{text}'") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be at least {low}, got {value}")
        if high is not None and value > high:
            raise argparse.ArgumentTypeError(f"must be at most {high}, got {value}")
        return value
    return parse


MAX_BATCH_SIZE = 256
"""The most views one optimizer step renders (``--batch-size``): a batch renders at once, so memory grows with it."""

SEED_MAX = 2**63 - 1
"""The largest random seed (torch's generators take a signed 64-bit one)."""


def seed(text: str) -> int:
    """An argparse type: a random seed, an integer in [0, 2⁶³ − 1]."""
    return int_at_least(0, SEED_MAX)(text)


def finite_float(text: str) -> float:
    """An argparse type: a finite number."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got '{text}'") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def float_in(low: float, high: float, *, low_open: bool = True, high_open: bool = False):
    """An argparse type: a finite number in the interval from ``low`` to ``high`` (open or closed ends)."""
    def parse(text: str) -> float:
        value = finite_float(text)
        if (value <= low if low_open else value < low) or (value >= high if high_open else value > high):
            interval = f"{'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
            raise argparse.ArgumentTypeError(f"must lie in {interval}, got {text}")
        return value
    return parse


positive_float = float_in(0.0, math.inf, high_open=True)


def int_in(low: int, high: int):
    """An argparse type: an integer in [``low``, ``high``]."""
    at_least = int_at_least(low)

    def parse(text: str) -> int:
        value = at_least(text)
        if value > high:
            raise argparse.ArgumentTypeError(f"must be at most {high}, got {value}")
        return value
    return parse


def add_force_argument(p: argparse.ArgumentParser) -> None:
    """``--force``: let outputs replace existing files inside a dataset folder (see :mod:`omg4.app.outputs`)."""
    p.add_argument("--force", action="store_true",
                   help="allow outputs to replace existing files inside a dataset folder (never the inputs)")


def add_scene_arguments(p: argparse.ArgumentParser, positional: bool = True) -> None:
    """DATA and the reader options (format, resolution, frame range, camera subset)."""
    if positional:
        p.add_argument("data", type=Path, help="dataset folder (N3DV, D-NeRF/Blender or Panoptic layout)")
    add_format_argument(p)
    p.add_argument("--downscale", type=positive_float, default=1.0, help="divide the image resolution by this factor")
    p.add_argument("--frames", type=str, help="frame range START:END (end exclusive), e.g. 0:60")
    p.add_argument("--cameras", type=str, help="comma-separated camera names to use (default: all)")


def add_format_argument(p: argparse.ArgumentParser) -> None:
    """``--format``: force one of the dataset readers (:data:`omg4.data.readers.READERS`)."""
    from omg4.data.readers import READERS

    p.add_argument("--format", choices=list(READERS), help="force the dataset reader")


def add_paper_argument(p: argparse.ArgumentParser) -> None:
    """``--paper``: the paper's way in one switch (:mod:`omg4.compress.modes`)."""
    p.add_argument("--paper", action="store_true", default=None,
                   help="the paper's way: every choice where omg4 goes beyond the paper takes the paper's value "
                        "(SD-score ranking and uniform view sampling, the paper's coder, segments coded alone; "
                        "docs/paper-map.md, Part E); a flag naming one of them still sets it")


def add_codec_argument(p: argparse.ArgumentParser, *, from_settings: bool = False) -> None:
    """``--codec``: the ``.omg4`` file coder (:data:`omg4.codec.coders.CODERS`, the first is the default; with
    ``from_settings`` an unset flag stays None, for a config file to choose)."""
    from omg4.codec.coders import CODERS

    p.add_argument("--codec", default=None if from_settings else next(iter(CODERS)), choices=list(CODERS),
                   help="file coder: compact (default: codewords coded without their order, unit quaternions, "
                        "8-bit MLP weights: about half the paper coder's file at the same quality, docs/results.md), "
                        "ans (lossless, fp16 values as the paper), paper (Huffman + LZMA as OMG4)")


def compact_grids(text: str):
    """An argparse type: the compact codec's grids, ``POSITIONS,ROTATIONS,TIMES[,WEIGHTS,LOG_SCALES[,CODEBOOKS[,EXACT]]]``
    or a name (:class:`omg4.codec.coders.CompactGrids`)."""
    from omg4.codec.payload import CompactGrids
    from omg4.errors import OMG4Error

    try:
        return CompactGrids.parse(text)
    except OMG4Error as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


GRID_BITS_HELP = ("beyond the paper: the compact codec's grids, bits per position axis (0: fp16), per quaternion "
                  "component (16: the rotation codebooks), of the clip's duration per time step (0: fp16), and "
                  "optionally per MLP weight (2-8, or 16: fp16), of log-scale codebook steps (0: unrounded), of the "
                  "other codebooks' steps (0: unrounded) and the percentage of Gaussians, the largest, whose positions "
                  "are kept exactly (0: none); default 15,9,10 = 15,9,10,8,5,0,3; coarser grids (e.g. 15,8,8 or "
                  "12,7,7) make smaller files at some quality; lossless (= 0,16,0,16,0) holds the paper coder's "
                  "values exactly, in fewer bytes (sizes and PSNR of each: docs/results.md)")


rate_weight = float_in(0.0, math.inf, low_open=False, high_open=True)
"""An argparse type: a rate weight β, finite and ≥ 0."""


def rate_weight_list(text: str) -> tuple[float, ...]:
    """An argparse type: comma-separated distinct rate weights (each finite and ≥ 0), in the order given."""
    values = tuple(rate_weight(part.strip()) for part in text.split(","))
    if len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(f"rate weights must be distinct, got {text}")
    return values


def add_rate_weight_argument(p: argparse.ArgumentParser) -> None:
    """``--rate-weight``: β of entropy-constrained SVQ codebooks (:class:`omg4.compress.pipeline.CompressConfig`)."""
    p.add_argument("--rate-weight", type=rate_weight, metavar="BETA",
                   help="beyond the paper: fit the codebooks by entropy-constrained k-means, an index bit costing "
                        "BETA times the mean k-means distortion, so the indices code to fewer bits at some quality "
                        "(docs/results.md); 0 (default) is the paper's k-means")


def add_device_arguments(p: argparse.ArgumentParser, backend: bool = True, *, from_settings: bool = False) -> None:
    """``--device`` (where models, images and optimizers live) and, with ``backend``, the rasterizer ``--backend``.

    ``from_settings``: unset flags stay None, so a command's config file can choose them
    (:func:`fill_device_arguments`)."""
    from omg4.device import DEVICE_HELP
    from omg4.kernels import KERNEL_MODES
    from omg4.render.rendered import BACKENDS

    if backend:
        p.add_argument("--backend", default=None if from_settings else "auto", choices=list(BACKENDS),
                       help="rasterizer: auto (gsplat on cuda, the numba CPU rasterizer on cpu; the default), cpu, "
                            "or gsplat (cuda only)")
    p.add_argument("--device", default=None if from_settings else "cpu",
                   help=f"where to compute (default cpu): {DEVICE_HELP}")
    # not in --help (a check of the kernels): the per-Gaussian work on the fused numba kernels on the CPU (fused, the
    # default; $OMG4_KERNELS) or as the pure-torch reference they are tested against (reference); a command with a
    # config (train, compress) records it there as its ``kernels`` setting
    p.add_argument("--kernels", choices=list(KERNEL_MODES), default=None, help=argparse.SUPPRESS)


def fill_device_arguments(args, settings: dict) -> None:
    """``--device`` and ``--backend`` left unset take the settings' values (removed from ``settings``), else cpu
    and auto."""
    for name, default in (("device", "cpu"), ("backend", "auto")):
        value = settings.pop(name, None)
        if getattr(args, name, None) is None:
            setattr(args, name, value or default)


def device_from_args(args):
    """The torch device of ``--device``, checked against ``--backend`` when the command has one; ``$OMG4_KERNELS``
    checked (``--kernels`` is chosen by :func:`omg4.app.cli.main` for the command).

    Raises a one-line :class:`OMG4Error` for an unusable device or a backend that cannot
    render there (the cpu rasterizer on CUDA, gsplat off CUDA).
    """
    from omg4.device import resolve_device
    from omg4.errors import OMG4Error
    from omg4.kernels import kernel_mode
    from omg4.render.api import resolve_backend

    try:
        kernel_mode()
    except ValueError as exc:
        raise OMG4Error(str(exc)) from None
    device = resolve_device(args.device)
    backend = getattr(args, "backend", "auto")
    if backend == "gsplat" and device.type != "cuda":
        raise OMG4Error(f"--backend gsplat renders on CUDA, not on {device}: add --device cuda")
    resolve_backend(backend, device)
    return device


def config_from_args(config_class, args, **values):
    """``config_class`` (a dataclass) from the parsed arguments whose names are its fields, plus ``values``
    (fields computed by the command); arguments left unset (``None``) keep the dataclass default."""
    from dataclasses import fields

    given = {f.name: getattr(args, f.name) for f in fields(config_class) if getattr(args, f.name, None) is not None}
    return config_class(**{**given, **values})


def parse_frames(text: str | None) -> range | None:
    """``"a:b"`` → range(a, b); ``None`` → None."""
    if not text:
        return None
    from omg4.errors import OMG4Error

    try:
        a, b = text.split(":")
        return range(int(a or 0), int(b))
    except ValueError:
        raise OMG4Error(f"--frames expects START:END, got '{text}'") from None


def add_background_argument(p: argparse.ArgumentParser) -> None:
    """``--white-background``: composite RGBA images over white and render on white (default black)."""
    p.add_argument("--white-background", action="store_true",
                   help="composite RGBA images (D-NeRF/Blender) over white and render on white (default: black)")


def background_from_args(args) -> tuple[float, float, float]:
    """The RGB background of ``--white-background`` (black when the command has no such option)."""
    return (1.0, 1.0, 1.0) if getattr(args, "white_background", False) else (0.0, 0.0, 0.0)


def load_scene_from_args(args, *, decode: bool = True, background: tuple[float, float, float] | None = None,
                         frames: range | None = None):
    """The scene named by ``args.data`` with the reader options of :func:`add_scene_arguments`, its RGBA
    images composited over ``background`` (default: that of :func:`background_from_args`; ``decode=False``:
    cameras and times only, no frame decoded); ``frames`` replaces ``--frames``."""
    from omg4.data import load_scene

    cameras = [c.strip() for c in args.cameras.split(",")] if getattr(args, "cameras", None) else None
    return load_scene(args.data, format=args.format, downscale=args.downscale,
                      frames=frames if frames is not None else parse_frames(args.frames), cameras=cameras,
                      background=background or background_from_args(args), decode=decode, progress=decode)


def segment_scenes(args, background: tuple[float, float, float]):
    """``load(start, stop)``: the frames ``[start, stop)`` of ``args.data`` as a scene (rank 0 reads first), for
    :func:`omg4.train.segmented.train_segments` and :func:`omg4.compress.api.compress_segments`."""
    from omg4 import distributed

    return lambda start, stop: distributed.main_first(
        lambda: load_scene_from_args(args, background=background, frames=range(start, stop)))


def printable(value: object) -> str:
    """``str(value)`` with control and other non-printing characters escaped (``\\x1b``, ``\\n``, ...), so names
    and messages that come from files cannot move the cursor, recolour the terminal or break a line."""
    text = str(value)
    return "".join(c if unicodedata.category(c)[0] != "C" else repr(c)[1:-1] for c in text)


def add_settings_arguments(p: argparse.ArgumentParser, config_class, *, shortcuts: tuple[str, ...], section: str,
                           defaults: str = "the defaults") -> None:
    """``--config FILE``, ``--set KEY=VALUE``, ``--settings`` (every field of ``config_class`` listed, then exit) and
    one ``--field-name`` flag per field (dotted nested fields: ``--merge-grid-size``) that the command's own flags
    (``shortcuts``) do not already set; those flags are left out of ``--help``, which shows what users change, and
    ``--settings`` lists them all.

    Precedence (:func:`settings_from_args`): the preset < the file < ``--set`` < the flags.
    """
    from omg4.settings import settings_of

    p.add_argument("--config", type=Path, metavar="FILE",
                   help=f"settings from a TOML or JSON file: {config_class.__name__} field names and values "
                        f"(a run's own record, which holds them under '{section}', reproduces the run)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", dest="settings",
                   help="one setting by its field name (repeatable; values as JSON, e.g. background=[1,1,1], "
                        "merge.grid_size=0.2); --settings lists them")
    table = settings_of(config_class)
    p.add_argument("--settings", action=_ListSettings, nargs=0, table=table, defaults=defaults,
                   help=f"list every setting --set and --config take ({config_class.__name__}: learning rates, "
                        "schedules and the like, with their defaults) and exit")
    for name, setting in table.items():
        if name not in shortcuts:
            p.add_argument(_setting_flag(name), dest=_setting_dest(name), type=_setting_type(name, setting.type),
                           help=argparse.SUPPRESS)
    for old, new in getattr(config_class, "MOVED_SETTINGS", {}).items():  # earlier flags, read as deprecated names
        if old not in shortcuts and new not in shortcuts:
            p.add_argument(_setting_flag(old), dest=_setting_dest(old), type=_setting_type(old, table[new].type),
                           help=argparse.SUPPRESS)


class _ListSettings(argparse.Action):
    """``--settings``: print every setting (name, type, default, meaning) and exit."""

    def __init__(self, *args, table, defaults: str, **kwargs):
        super().__init__(*args, **kwargs)
        self.table, self.defaults = table, defaults

    def __call__(self, parser, namespace, values, option_string=None):
        from omg4.settings import type_name

        print(f"settings ({self.defaults}); set one with --set NAME=VALUE, several in a --config file, or as "
              "--NAME-WITH-DASHES VALUE:")
        width = max(len(name) for name in self.table)
        try:
            for name, setting in self.table.items():
                default = "" if setting.default is None else f", default {setting.default}"
                print(f"  {name:<{width}}  {setting.help} ({type_name(setting.type)}{default})")
        except BrokenPipeError:  # piped into a pager or `head` that closed early
            sys.stderr.close()
        parser.exit()


def _setting_flag(name: str) -> str:
    return "--" + name.replace(".", "-").replace("_", "-")


def _setting_dest(name: str) -> str:
    return "setting:" + name


def _setting_type(name: str, kind):
    from omg4.settings import convert

    def parse(text: str):
        from omg4.errors import OMG4Error

        try:
            value = json.loads(text)
        except ValueError:
            value = text
        try:
            return convert(name, value, kind)
        except OMG4Error as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    return parse


def settings_from_args(args, config_class, *, section: str, extra: tuple[str, ...] = ()) -> dict:
    """The checked flat settings of :func:`add_settings_arguments`: the ``--config`` file, then ``--set``, then the
    per-field flags (later ones win); the command's own flags are applied by the command, last."""
    from omg4.settings import check_settings, parse_assignments, read_config_file

    values = read_config_file(args.config, section, extra) if args.config else {}
    values.update(parse_assignments(args.settings))
    values.update({k[len("setting:"):]: v for k, v in vars(args).items() if k.startswith("setting:") and v is not None})
    return check_settings(config_class, values, extra=extra)


def add_distributed_arguments(p: argparse.ArgumentParser, *, replicas: bool = True) -> None:
    """``--nproc N`` (run as N ranks on this machine, as ``torchrun --nproc-per-node N -m omg4`` does) and, with
    ``replicas``, ``--check-replicas K`` (compare the ranks' parameters every K steps; a debugging aid)."""
    p.add_argument("--nproc", type=int_at_least(1), metavar="N",
                   help="run as N processes on this machine (torch.distributed: gloo on cpu, one GPU each on cuda); "
                        "for several machines start the same command with torchrun")
    if replicas:  # a debugging aid, not in --help: compare a hash of every rank's parameters every K steps (0: never)
        p.add_argument("--check-replicas", type=int_at_least(0), default=0, metavar="K", help=argparse.SUPPRESS)
