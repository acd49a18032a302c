"""argparse types shared by the command-line modules (:mod:`difstar.cli`): numbers checked by
:func:`difstar._validate.check_number`, so the command line refuses what the Python API
refuses, with the same message (argparse adds the option's name)."""

from __future__ import annotations

import argparse

from .._validate import InputError, check_number


def arg_type(name: str, **limits):
    """An argparse ``type``: a finite number within ``limits`` (message names the
    limit; argparse adds the option's name)."""
    integer = limits.pop("integer", False)

    def parse(text: str):
        try:
            v = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{text!r} is not {'an integer' if integer else 'a number'}") from None
        try:
            return check_number(v, "value", integer=integer, **limits)
        except InputError as exc:
            raise argparse.ArgumentTypeError(str(exc).split(": ", 1)[1]) from None

    parse.__name__ = name
    return parse


positive_int = arg_type("positive_int", integer=True, ge=1)
nonnegative_int = arg_type("nonnegative_int", integer=True, ge=0)
finite_float = arg_type("finite_float")
positive_float = arg_type("positive_float", gt=0)
nonnegative_float = arg_type("nonnegative_float", ge=0)
