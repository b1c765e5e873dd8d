"""The ``recal`` command line (contracts §6, docs/contracts.md).

Each verb lives in its own module under ``service/commands/`` with ``add_parser(sub)`` and
``run(args)``; the module is imported only when its verb runs, so ``recal`` starts fast and the
math verbs never import the web stack. On bad input a verb raises ``InputError`` (or
``Fail``): ``recal`` prints one line on stderr naming the file, row and column (or JSON field)
at fault, exits with status 2 and writes no output file.
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import os
import sys

from calibration.errors import RecalError

# Recal's matrices are small (tens of parameters): on a shared machine a multithreaded BLAS
# spends more time synchronising threads than computing (measured ~25x slower on 2 cores).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# verb -> (module under service.commands, one-line help). Add a verb: add a module and a line.
COMMANDS: dict[str, tuple[str, str]] = {
    "identify": ("identify", "identify a model's parameters from measurements"),
    "cpa": ("cpa", "circle-point analysis: joint axes from single-joint sweeps, then a model"),
    "predict": ("predict", "tool poses (or target positions) for joint readings"),
    "plan": ("plan", "choose the configurations to measure, and predict the accuracy they give"),
    "export": ("export", "write a model as URDF or as a DH table (CSV, Markdown)"),
    "compensate": ("compensate", "compensated task files (CSV or URScript) for an identified robot"),
    "accuracy": ("accuracy", "ISO 9283 pose accuracy and repeatability of measurements against a model"),
    "model": ("model", "list library robots, or write one's nominal model"),
    "controller-model": ("controller_model", "read a UR controller's own kinematics (factory calibration) over RTDE"),
    "demo": ("demo", "the main job: a whole calibration, end to end, on a simulated robot"),
    "serve": ("serve", "run the REST API (docs/contracts.md §9, docs/service.md)"),
    "token": ("token", "create API tokens"),
    "repair-text": ("repair_text", "find (--check) or repair stored text that cannot be read"),
    "backup": ("backup", "a consistent copy of the embedded SQLite store, while the service runs"),
    "nightly": ("nightly", "check a cell's accuracy and recalibrate it when it drifted"),
    "worker": ("worker", "run the sessions of some sites' cells (the fleet, docs/fleet.md)"),
}


class Fail(RecalError):
    """A one-line failure for the user (exit status 2)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2, without argparse's usage dump
        self.exit(2, f"{self.prog}: {message} (see `{self.prog} --help`)\n")

    def check_flags(self, args: list[str]) -> None:
        """Name the first long flag in ``args`` that this parser does not know, with the nearest one
        it does (exit 2). argparse would first complain of a required flag the misspelt one was
        meant to be (``--modle`` -> "required: --model") and never name the typo."""
        known = [o for o in self._option_string_actions if o.startswith("--")]
        nested = {
            name: parser
            for action in self._actions
            if isinstance(action, argparse._SubParsersAction)
            for name, parser in action.choices.items()
        }
        for k, token in enumerate(args):
            if token == "--":  # what follows is positional
                return
            if token in nested:  # `recal token create --role ...`: the rest is the sub-command's
                if isinstance(nested[token], _Parser):
                    nested[token].check_flags(args[k + 1 :])
                return
            if not token.startswith("--"):
                continue
            flag = token.split("=", 1)[0]
            if flag in known or any(o.startswith(flag) for o in known):  # argparse takes unique prefixes
                continue
            near = _nearest(flag, known)
            self.error(f"unrecognized argument {flag}" + (f"; did you mean {near}?" if near else ""))


def _nearest(flag: str, known: list[str]) -> str | None:
    """The known flag a typo most likely meant: one with the same letters in another order first
    (``--modle`` is ``--model``, not ``--mode``), else the closest by difflib's ratio."""
    swapped = [o for o in known if sorted(o) == sorted(flag)]
    if swapped:
        return swapped[0]
    near = difflib.get_close_matches(flag, known, n=1, cutoff=0.6)
    return near[0] if near else None


def version() -> str:
    """The installed package's version (pyproject.toml's ``version``)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as installed

    try:
        return installed("recal")
    except PackageNotFoundError:  # a source tree that was never installed
        return "unknown (not installed: pip install -e .)"


# ``--quiet`` (every verb): no progress lines, even on a terminal.
_quiet = False


def progress(message: str) -> None:
    """Progress for long runs, only when a person is watching (stderr is a terminal) and did
    not ask for ``--quiet``: a script reading stderr sees only warnings and errors."""
    if not _quiet and sys.stderr.isatty():
        print(message, file=sys.stderr, flush=True)


def build_parser(verb: str | None = None) -> argparse.ArgumentParser:
    """The parser; with ``verb``, only that verb's module is imported."""
    p = _Parser(prog="recal", description="Robot calibration: identify, predict, compensate, simulate.")
    p.add_argument("--version", action="version", version=f"recal {version()}")
    sub = p.add_subparsers(dest="verb", required=True, parser_class=_Parser)
    for name, (module, help_text) in COMMANDS.items():
        if verb is None or name == verb:
            mod = importlib.import_module(f"service.commands.{module}")
            sp = sub.add_parser(name, help=help_text, description=help_text)
            mod.add_parser(sp)
            sp.add_argument("--quiet", action="store_true", help="no progress lines on stderr (shown on a terminal)")
            sp.set_defaults(func=mod.run)
        else:
            sub.add_parser(name, help=help_text, add_help=False)
    sub.add_parser(
        "fake-cell", help="run a simulated cell (docs/contracts.md §7); see `recal fake-cell --help`", add_help=False
    )
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "fake-cell":
        from fakes.cell import main as fake_cell

        return int(fake_cell(argv[1:]) or 0)
    if argv[:1] == ["--version"]:  # at once: without importing every verb's module for the help
        print(f"recal {version()}")
        return 0
    verb = argv[0] if argv and argv[0] in COMMANDS else None
    parser = build_parser(verb)
    if verb is None:
        parser.check_flags(argv[:1])
    else:
        subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        subparsers.choices[verb].check_flags(argv[1:])
    args = parser.parse_args(argv)
    from service.files import InputError
    from service.task_compensation import CompensationInputError

    global _quiet  # noqa: PLW0603 - one flag for the whole process (--quiet), set once per command
    _quiet = bool(getattr(args, "quiet", False))
    try:
        return int(args.func(args) or 0)
    except (InputError, Fail, CompensationInputError) as exc:
        print(f"recal {args.verb}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"recal {args.verb}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into `head`: not an error
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
