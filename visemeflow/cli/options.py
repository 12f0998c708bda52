"""A stage's command made from its params model: the command names the fields it offers, each option's type, default
and help come from the field, and its values become the params model (nested configs included) that the stage's
flow takes, checked by that model.

    @stage_command(app, TrackParams, [STORE, Opt("n_shards", "--shards"), Opt("config.solver"), ...])
    def track(params: TrackParams) -> None:
        ...

An option is one field of the model by its path (`config.solver`), offered as `--solver` (the path's last part,
dashed) unless named; a field's description is its help (what the Prefect UI's form shows beside the field too),
with a Literal's choices added. A list field is one comma-separated value (`--sizes 100,300`) or a repeated option
(`repeat=True`, for paths). An option that is not a field (`path=None`: a value only the command reads, such as an
output file) says its own type, default and help; one that fills other fields says how (`into`). A value the model
refuses is one line naming the option, exit 2, before any flow starts.
"""

from __future__ import annotations

import inspect
import types
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import PurePath
from typing import Annotated, Any, Literal, Optional

import click
import typer
from pydantic import BaseModel, ValidationError
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from visemeflow.logs import summary_prints_them

FROM_FIELD: Any = object()   # an Opt's type/default/help: the field's own


@dataclass(frozen=True)
class Opt:
    """One option (or positional argument) of a stage's command."""

    path: str | None
    flag: str | None = None
    help: str | None = None
    callback: Callable[..., Any] | None = None
    argument: bool = False
    repeat: bool = False
    default: Any = FROM_FIELD
    type: Any = FROM_FIELD
    into: Callable[[Any], dict[str, Any]] | None = None
    name: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)   # more typer.Option settings (min=..., show_default=...)

    @property
    def param_name(self) -> str:
        if self.name:
            return self.name
        if self.flag:
            return self.flag.lstrip("-").split("/")[0].replace("-", "_")
        assert self.path is not None, "an option that is not a field needs a flag or a name"
        return self.path.rsplit(".", 1)[-1]

    @property
    def flag_name(self) -> str:
        return self.flag or "--" + self.param_name.replace("_", "-")


def field_at(model: type[BaseModel], path: str) -> FieldInfo:
    """The field of `model` at a dotted path through nested models (`config.solver`)."""
    *parents, leaf = path.split(".")
    for part in parents:
        model = _model_of(model.model_fields[part].annotation)
    if leaf not in model.model_fields:
        raise KeyError(f"{model.__name__} has no field {leaf!r} (option path {path!r})")
    return model.model_fields[leaf]


def _model_of(annotation: Any) -> type[BaseModel]:
    for candidate in (annotation, *typing.get_args(annotation)):
        if isinstance(candidate, type) and issubclass(candidate, BaseModel):
            return candidate
    raise TypeError(f"{annotation!r} is not a nested params model")


def _strip(annotation: Any) -> tuple[Any, bool]:
    """(the annotation without None and Annotated metadata, whether None was allowed)."""
    optional = False
    origin = typing.get_origin(annotation)
    if origin is Annotated:
        return _strip(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        optional = len(args) < len(typing.get_args(annotation))
        inner, _ = _strip(args[0]) if len(args) == 1 else (str, False)
        return inner, optional
    return annotation, optional


def _is_list(annotation: Any) -> bool:
    return typing.get_origin(annotation) in (list, tuple, set, frozenset, Sequence)


def _item_type(annotation: Any) -> Any:
    args = [a for a in typing.get_args(annotation) if a is not Ellipsis]
    return _cli_type(args[0]) if args else str


def _cli_type(annotation: Any) -> Any:
    """What typer parses a value of this field as: Literals and unknown types as text, the model checks them."""
    annotation, _ = _strip(annotation)
    if typing.get_origin(annotation) is Literal:
        return str
    if annotation in (str, int, float, bool):
        return annotation
    return annotation if isinstance(annotation, type) and issubclass(annotation, PurePath) else str


def _choices(annotation: Any) -> tuple[str, ...]:
    annotation, _ = _strip(annotation)
    if _is_list(annotation):
        return _choices(typing.get_args(annotation)[0]) if typing.get_args(annotation) else ()
    return tuple(map(str, typing.get_args(annotation))) if typing.get_origin(annotation) is Literal else ()


_FACTORY: Any = object()   # a field whose default a factory makes (never called here: it may import a lot)


def _field_default(info: FieldInfo) -> Any:
    if info.default is not PydanticUndefined:
        return info.default
    return _FACTORY if info.default_factory is not None else ...   # ...: required


def _shown(default: Any) -> Any:
    """A field's default as an option shows it: a list or tuple as its comma-separated text."""
    if isinstance(default, (list, tuple)) and all(isinstance(x, (str, int, float)) for x in default):
        return ",".join(map(str, default))
    return default


@dataclass(frozen=True)
class _Resolved:
    opt: Opt
    annotation: Any
    default: Any
    help: str
    is_list: bool
    choices: tuple[str, ...] = ()
    none_word: bool = False
    """A number that may be None but defaults to a number: the value `none` on the command line sets None."""


def _resolve(model: type[BaseModel], opt: Opt) -> _Resolved:
    info = field_at(model, opt.path) if opt.path else None
    if info is None and (opt.type is FROM_FIELD or opt.default is FROM_FIELD or opt.help is None):
        raise TypeError(f"option {opt.flag_name} is no field of {model.__name__}: give its type, default and help")
    field_type = info.annotation if info is not None else None
    stripped, optional = _strip(field_type) if info is not None else (None, False)
    is_list = opt.type is FROM_FIELD and info is not None and _is_list(stripped)
    if opt.type is not FROM_FIELD:
        annotation = opt.type
    elif is_list:
        annotation = list[_item_type(stripped)] if opt.repeat else str
        if not (opt.argument and _field_default(info) is ...):   # a required argument stays one: `AUDIO...`
            annotation = Optional[annotation]   # noqa: UP007 (typer reads Optional)
    else:
        annotation = _cli_type(field_type)
        if optional:
            annotation = Optional[annotation]   # noqa: UP007
    none_word = (opt.type is FROM_FIELD and not is_list and optional and stripped in (int, float)
                 and _field_default(info) not in (None, _FACTORY, ...))
    if none_word:
        annotation = Optional[str]   # noqa: UP007 (a number or `none`; the model parses the number)
    if opt.default is not FROM_FIELD:
        default = opt.default
    else:
        default = _field_default(info)
        if default is _FACTORY:
            default = None
        if is_list and not (opt.argument and default is ...):
            default = None if opt.repeat or default in ((), []) else _shown(default)
    text = opt.help if opt.help is not None else (info.description or "")
    choices = _choices(field_type) if info is not None else ()
    if choices and opt.help is None and "one of" not in text.lower():
        text = f"{text} {'Any' if is_list else 'One'} of: {', '.join(choices)}.".strip()
    limits = _limits(info) if info is not None and not is_list else ""
    if limits:
        text = f"{text} ({limits})"
    if none_word and "none" not in text.lower().split():
        text = f"{text} none: no value (None)."
    if opt.repeat and not opt.argument and "repeat" not in text.lower():
        text = f"{text} Repeat for several.".strip()
    return _Resolved(opt, annotation, default, text, is_list, choices, none_word)


_LIMIT_WORDS = (("ge", "at least"), ("gt", "above"), ("le", "at most"), ("lt", "below"))


def _limits(info: FieldInfo) -> str:
    """A field's numeric bounds in words ("at least 1, at most 4096"), as its model checks them."""
    found = []
    for constraint in info.metadata:
        for attr, words in _LIMIT_WORDS:
            value = getattr(constraint, attr, None)
            if value is not None:
                found.append(f"{words} {value:g}" if isinstance(value, (int, float)) else f"{words} {value}")
    return ", ".join(found)


def _metavar(annotation: Any, is_list: bool, repeat: bool, none_word: bool = False) -> str | None:
    """The word that stands for an option's value in the help: FILE-like paths, N, X, TEXT, A,B for a list."""
    if is_list and not repeat:
        return "A,B"
    inner, _ = _strip(annotation)
    if typing.get_origin(inner) is list:
        inner = typing.get_args(inner)[0]
    if inner is bool:
        return None
    if none_word:
        return "N|none"
    if isinstance(inner, type) and issubclass(inner, PurePath):
        return "PATH"
    return {int: "N", float: "X"}.get(inner, "TEXT")


def _one_of(flag: str, choices: tuple[str, ...], then: Callable[..., Any] | None, listed: bool) -> Callable[..., Any]:
    """A callback refusing a value (or, for a list, a comma-separated item) outside a Literal's choices in one line,
    exit 2, before any flow starts; then the option's own callback."""
    def check(ctx: typer.Context, value: Any) -> Any:
        if not ctx.resilient_parsing and value is not None:
            items = value if isinstance(value, list) else value.split(",") if listed else [value]
            wrong = [str(v).strip() for v in items if str(v).strip() not in choices]
            if wrong:
                typer.echo(f"error: {flag} must be one of {', '.join(choices)}, not {wrong[0]!r}", err=True)
                raise typer.Exit(2)
        return then(ctx, value) if then is not None else value
    return check


def _typer_param(r: _Resolved) -> inspect.Parameter:
    opt = r.opt
    callback = _one_of(opt.flag_name, r.choices, opt.callback, r.is_list) if r.choices else opt.callback
    metavar = _metavar(r.annotation, r.is_list, opt.repeat, r.none_word)
    if opt.argument:
        info = typer.Argument(help=r.help, callback=callback, metavar=opt.param_name.upper(), **opt.extra)
    elif metavar is not None:
        info = typer.Option(opt.flag_name, help=r.help, callback=callback, metavar=metavar, **opt.extra)
    else:
        flag = opt.flag_name
        if _strip(r.annotation)[0] is bool and "/" not in flag:
            flag = f"{flag}/--no-{flag[2:]}"   # on and off, as typer names a bool option of its own
        info = typer.Option(flag, help=r.help, callback=callback, **opt.extra)
    default = inspect.Parameter.empty if r.default is ... else r.default
    return inspect.Parameter(opt.param_name, inspect.Parameter.KEYWORD_ONLY, default=default,
                             annotation=Annotated[r.annotation, info])


def _set(tree: dict[str, Any], path: str, value: Any) -> None:
    *parents, leaf = path.split(".")
    for part in parents:
        tree = tree.setdefault(part, {})
    tree[leaf] = value


def _value(r: _Resolved, value: Any) -> Any:
    if r.is_list and isinstance(value, str):
        return [x.strip() for x in value.split(",") if x.strip()]
    if r.none_word and isinstance(value, str):
        return None if value.strip().lower() in ("none", "null") else value.strip()
    return value


def build_params(model: type[BaseModel], options: Sequence[Opt], values: dict[str, Any]) -> BaseModel:
    """The params model from the command's option values: each field option's value at its path, the `into`
    options' fields, and None left out where the field has a default of its own (a default character, a config
    made by a factory), so the model's default stands. A value the model refuses: one line naming the option and
    exit 2."""
    tree: dict[str, Any] = {}
    flags: dict[str, str] = {}
    for opt in options:
        value = values.get(opt.param_name)
        if opt.into is not None:
            for path, v in opt.into(value).items():
                _set(tree, path, v)
                flags[path] = opt.flag_name
            continue
        if opt.path is None:
            continue
        flags[opt.path] = opt.param_name.upper() if opt.argument else opt.flag_name
        info = field_at(model, opt.path)
        if value is None and _field_default(info) is not None:
            continue
        r = _resolve(model, opt)
        _set(tree, opt.path, _value(r, value))
    try:
        return model.model_validate(tree)
    except ValidationError as exc:
        error = exc.errors()[0]
        loc = ".".join(str(p) for p in error["loc"] if not isinstance(p, int))
        # the option of the refused field (or of a field inside it); none for a rule over several fields
        where = flags.get(loc) or next((f for p, f in flags.items() if loc.startswith(p + ".")), None)
        if error["type"] == "missing":
            typer.echo(f"error: {where or loc} is required", err=True)
            raise typer.Exit(2) from None
        message = error["msg"].removeprefix("Value error, ")
        typer.echo(f"error: {where}: {message}" if where else f"error: {message}", err=True)
        raise typer.Exit(2) from None


def stage_command(app: typer.Typer, model: type[BaseModel], options: Sequence[Opt], name: str | None = None,
                  prints_rejects: bool = True,
                  **command_settings: Any) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Register the decorated function as the command `name` (default: its own name, dashed) whose options are
    `options` of `model`; it is called with the params model and, by name, the options that are not fields.
    `prints_rejects`: the command ends by printing its rejects and its packages' warnings, so Prefect's console
    leaves those lines to it (`visemeflow.logs`; a command that fails first gets them on the console after all)."""
    resolved = [_resolve(model, opt) for opt in options]
    names = [r.opt.param_name for r in resolved]
    if len(set(names)) != len(names):
        raise ValueError(f"{model.__name__}: two options share a name in {names}")

    def register(body: Callable[..., Any]) -> Callable[..., Any]:
        own = [r.opt.param_name for r in resolved if r.opt.path is None and r.opt.into is None]

        def command(**values: Any) -> Any:
            params = build_params(model, options, values)
            if not prints_rejects:
                return body(params, **{k: values[k] for k in own})
            with summary_prints_them((SystemExit, typer.Exit, click.exceptions.Exit)):   # it prints them, once
                return body(params, **{k: values[k] for k in own})

        command.__signature__ = inspect.Signature([_typer_param(r) for r in resolved])  # type: ignore[attr-defined]
        command.__doc__ = body.__doc__
        command.__name__ = body.__name__
        command.__qualname__ = body.__qualname__
        command.options = tuple(options)   # type: ignore[attr-defined]
        command.params_model = model       # type: ignore[attr-defined]
        app.command(name or body.__name__.replace("_", "-"), **command_settings)(command)
        return command

    return register
