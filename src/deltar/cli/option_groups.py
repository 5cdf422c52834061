"""Option groups: several command-line options that one dataclass parameter stands for.

A command declares one parameter (``model: ModelOptions = MODEL_OPTIONS``) and is
decorated with the group's decorator; the decorator puts the group's options in its
place (the same names, types and help in every command that takes the group) and hands
the command one object. :mod:`deltar.cli.model_options` and the bag topic options of
:mod:`deltar.cli.robotics` are such groups.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable, Mapping
from dataclasses import fields
from typing import Any


def option_group(parameter: str, group: type, option_types: Mapping[str, Any]
                 ) -> Callable[[Callable], Callable]:
    """A decorator replacing a command's ``parameter`` by one option per field of ``group``.

    Args:
        parameter: the command's parameter that stands for the group (e.g. ``"model"``).
        group: a dataclass whose fields (with their defaults) are the options.
        option_types: field name -> the typer annotation of its option
            (``Annotated[type, typer.Option(...)]``).

    Returns:
        The decorator: the options appear where ``parameter`` stands in the command's
        signature; the command receives ``parameter=group(...)``.

    Raises:
        TypeError: (by the decorator) a command without ``parameter``.
    """
    options = [inspect.Parameter(f.name, inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                 default=f.default, annotation=option_types[f.name])
               for f in fields(group)]

    def decorate(command: Callable) -> Callable:
        signature = inspect.signature(command, eval_str=True)
        params = list(signature.parameters.values())
        names = [p.name for p in params]
        if parameter not in names:
            raise TypeError(f"{command.__name__} has no {parameter!r} parameter")
        at = names.index(parameter)
        params[at:at + 1] = options

        @functools.wraps(command)
        def wrapper(**kwargs):
            value = group(**{p.name: kwargs.pop(p.name) for p in options})
            return command(**{parameter: value}, **kwargs)

        wrapper.__signature__ = signature.replace(parameters=params)
        wrapper.__annotations__ = {p.name: p.annotation for p in params}
        return wrapper

    return decorate
