"""The argument parser of every console script (``epos-link``, ``tcp-bridge``).

The project's rule for a bad argument is one line naming the problem and exit 2.
argparse's own ``error()`` prints the usage block first (up to seven lines for
``epos-link read``, whose usage lists every ``--type``), and the message is last,
where a reader looks least. :class:`OneLineParser` prints only::

    epos-link read: argument NODE: node ids are 0..127, got 200 (see epos-link read --help)

``add_subparsers()`` makes its subparsers of the parser's own class, so building
the top-level parser with it is enough for every subcommand. ``--help`` is
argparse's, unchanged.

Unrecognised arguments are the one error argparse raises from the top-level
parser after a subcommand parsed: :meth:`OneLineParser.parse_args` reports them
from the subcommand they were given to, so the line and its ``--help`` hint name it.
"""
from __future__ import annotations

import argparse
import difflib
from typing import Any, NoReturn, Optional, Sequence


class OneLineParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line on stderr and exit status 2."""

    def error(self, message: str) -> NoReturn:
        # A message never spans lines today; joining keeps the promise if one ever does.
        text = " ".join(part.strip() for part in message.splitlines() if part.strip())
        self.exit(2, f"{self.prog}: {text} (see {self.prog} --help)\n")

    def _check_value(self, action: argparse.Action, value: Any) -> None:
        """argparse's check, plus the nearest choice for a typo: ``epos-link reed`` ->
        ``invalid choice: 'reed' (did you mean 'read'? choose from 'read', ...)``."""
        choices = action.choices
        if choices is not None and value not in choices and isinstance(value, str):
            names = [str(c) for c in choices]
            close = difflib.get_close_matches(value, names, n=1, cutoff=0.6)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise argparse.ArgumentError(action, f"invalid choice: {value!r} ({hint}choose from "
                                                 f"{', '.join(repr(n) for n in names)})")
        super()._check_value(action, value)  # type: ignore[misc]

    # typeshed overloads parse_args on the namespace's type; one Any signature serves all.
    def parse_args(self, args: Optional[Sequence[str]] = None,  # type: ignore[override]
                   namespace: Any = None) -> Any:
        namespace, extras = self.parse_known_args(args, namespace)
        if extras:
            self.chosen(namespace).error(f"unrecognized arguments: {' '.join(extras)}")
        return namespace

    def chosen(self, namespace: argparse.Namespace) -> argparse.ArgumentParser:
        """The innermost subcommand's parser that ``namespace`` came from (else this one)."""
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                sub = action.choices.get(str(getattr(namespace, action.dest, "")))
                if isinstance(sub, OneLineParser):
                    return sub.chosen(namespace)
                if sub is not None:
                    return sub
        return self


__all__ = ["OneLineParser"]
