"""The ``omg4`` command: parses arguments, calls library functions, prints.

Each subcommand lives in ``omg4.app.commands.<module>`` with two functions,
``configure(parser)`` and ``run(args) -> int``; only the chosen one is imported, so
``omg4 --help`` and ``omg4 info`` start fast. Errors of the user's making
(:class:`omg4.errors.OMG4Error`) print one line and exit 2.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import sys
from typing import Iterator

# Idle OpenMP threads must not spin: on small machines shared with other work, torch's default busy-waiting
# makes small-image ops many times slower (benchmarks/speed/metrics.py; docs/results.md).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# name -> (module in omg4.app.commands, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("demo", "the whole pipeline on a built-in synthetic scene (synth, train, compress, decode, eval)"),
    "synth": ("synth", "write the built-in procedural dynamic scene in N3DV layout"),
    "prepare": ("prepare", "your own capture: raw multi-view videos → a synchronized, calibrated dataset"),
    "info": ("info", "summary of a dataset folder, a checkpoint or an .omg4 file"),
    "train": ("train", "train a Real-Time4DGS or FreeTimeGS baseline"),
    "import-rt4dgs": ("import_rt4dgs", "convert an official Real-Time4DGS checkpoint"),
    "compress": ("compress", "run the OMG4 pipeline and write the compressed .omg4 file"),
    "eval": ("eval", "PSNR, SSIM, LPIPS, FPS, Gaussian count and storage on the test views"),
    "render": ("render", "render an image (.png/.npy), a video or a free-viewpoint video (.mp4)"),
    "export": ("export", "a time slice as a 3DGS .ply, or the 4D model as a .splatv for the splaTV web viewer"),
    "view": ("view", "interactive browser viewer: scrub time, fly the camera (needs the viewer extra: viser)"),
    "bench": ("bench", "ablation and size-preset benchmark on one scene"),
}


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: ``omg4 train: error: argument --iterations: ... (see omg4 train --help)``."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _build_parser(command: str | None) -> tuple[argparse.ArgumentParser, dict]:
    parser = _Parser(
        prog="omg4",
        description="OMG4: train, compress, decode, render and evaluate 4D Gaussian Splatting models.",
    )
    parser.add_argument("--version", action="version", version=f"omg4 {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    modules = {}
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == command:
            mod = importlib.import_module(f"omg4.app.commands.{module}")
            mod.configure(p)
            modules[name] = mod
    return parser, modules


def _version() -> str:
    from omg4 import __version__

    return __version__


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``omg4`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    if command not in COMMANDS:
        command = None
    from omg4.app.commands.common import printable
    from omg4.errors import OMG4Error

    try:
        parser, modules = _build_parser(command)
    except ModuleNotFoundError as e:  # an optional dependency of the command is not installed
        hint = install_hint(e.name or "")
        print(f"omg4: error: command '{command}' is not available ({e}{'; ' + hint if hint else ''})", file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    from omg4 import distributed

    if getattr(args, "nproc", None) and args.nproc > 1 and not distributed.launched():
        from omg4.app.launch import launch

        return launch(args.command, argv, args.nproc)
    from omg4.allocator import keep_freed_memory

    keep_freed_memory()
    from omg4.kernels import using_kernels

    try:
        with library_messages_shown(), using_kernels(getattr(args, "kernels", None)):  # for this command only
            status = int(modules[args.command].run(args) or 0)
        distributed.finish()
        if distributed.launched():
            distributed.leave(status)
        return status
    except OMG4Error as e:
        return _fail(args.command, printable(e), e)
    except MemoryError as e:
        return _fail(args.command, "out of memory (a smaller scene, model or image size may fit)", e)
    except ModuleNotFoundError as e:  # an optional dependency of what was asked for
        hint = install_hint(e.name or "")
        if hint is None:
            raise
        return _fail(args.command, f"this needs {e.name}, which is not installed: {hint}", e)
    except KeyboardInterrupt:
        print(f"omg4 {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into a pager or `head` that closed early
        sys.stderr.close()
        return 0


class _AboveProgressBars(logging.Handler):
    """Writes each message on its own line of standard output, above any progress bar."""

    def emit(self, record: logging.LogRecord) -> None:
        from tqdm.auto import tqdm

        tqdm.write(self.format(record), file=sys.stdout)


@contextlib.contextmanager
def library_messages_shown() -> Iterator[None]:
    """Inside, the library's messages (its ``omg4.*`` loggers, from INFO) are printed as the command runs; the
    library itself is quiet unless its caller asks (Python's logging)."""
    logger, handler = logging.getLogger("omg4"), _AboveProgressBars()
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


def install_hint(module: str) -> str | None:
    """The pip command that installs the optional dependency ``module`` (an extra of this package, read from its
    own metadata), or None when it is no optional dependency."""
    import importlib.metadata
    import re

    try:
        requirements = importlib.metadata.requires("omg4") or []
    except importlib.metadata.PackageNotFoundError:
        return None
    for requirement in requirements:
        match = re.fullmatch(r"([A-Za-z0-9_.-]+)([^;]*);\s*extra\s*==\s*[\"']([a-z]+)[\"']", requirement.strip())
        if match and match.group(1).lower().replace("-", "_") == module.split(".")[0].lower() \
                and match.group(3) != "dev":
            spec = match.group(1) + match.group(2).replace(" ", "")
            return f"pip install '{spec}' (the package's '{match.group(3)}' extra)"
    return None


def _fail(command: str, message: str, exc: BaseException) -> int:
    """One line on stderr (from rank 0 of a distributed job, or from the ``--nproc`` launcher; the other ranks leave
    their cause for it), exit 2."""
    from omg4 import distributed

    distributed.record_failure(exc)
    if distributed.reports_failures():
        print(f"omg4 {command}: error: {message}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
