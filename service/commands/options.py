"""Command-line options generated from the job's parameter models (the pipeline's
groups and the tiling), so that ``orchard process --help`` documents every parameter
with its unit and default, and a bound or a default is written only in the model."""

from __future__ import annotations

import argparse
import typing

if typing.TYPE_CHECKING:
    from pipeline.params import PipelineParams


def base_type(annotation):
    """``float`` for ``float | None``; other annotations unchanged."""
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    return args[0] if args and typing.get_origin(annotation) is not typing.Literal else annotation


def metavar(kind, description: str | None) -> str:
    """Placeholder of a numeric option in --help: N (a count), M (metres), GB or X."""
    units = {"[m]": "M", "[GB]": "GB"}
    return "N" if kind is int else next((v for k, v in units.items() if k in (description or "")), "X")


def add_pipeline_options(parser: argparse.ArgumentParser) -> None:
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from pipeline.params import GROUPS  # imported here: `orchard --help` needs no models

    for group, model in GROUPS.items():
        g = parser.add_argument_group(f"{group} parameters")
        for field_name, field in model.model_fields.items():
            flag = f"--{group}-{field_name}".replace("_", "-")
            ann = base_type(field.annotation)
            kwargs: dict = {"dest": f"p__{group}__{field_name}", "default": None}
            if typing.get_origin(ann) is typing.Literal:
                kwargs["choices"] = list(typing.get_args(ann))
            elif ann is bool:
                kwargs["action"] = argparse.BooleanOptionalAction
            elif ann in (int, float):
                kwargs["type"] = ann
                kwargs["metavar"] = metavar(ann, field.description)
            # argparse formats help with %: a literal % in a description must be doubled
            kwargs["help"] = f"{field.description} (default {field.default})".replace("%", "%%")
            g.add_argument(flag, **kwargs)


def pipeline_params_from_args(args: argparse.Namespace, base: PipelineParams | None = None) -> PipelineParams:
    """Build validated parameters from the options given (unset options keep defaults)."""
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from pipeline.params import PipelineParams

    data = (base or PipelineParams()).model_dump()
    for key, value in vars(args).items():
        if key.startswith("p__") and value is not None:
            _, group, field_name = key.split("__")
            data[group][field_name] = value
    return PipelineParams.model_validate(data)


def _origin(text: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in metres, not {text!r}") from None
    return x, y


def _tiling_field(name: str):
    """The field ``name`` of `TilingParams` (what a job computes), else of `RunOptions`
    (how it runs): the command line sets both with one group of options."""
    # here, not at the top: `orchard --help` imports every command module (see service.commands)
    from pipeline.jobparams import TilingParams
    from workers.runoptions import RunOptions

    return TilingParams.model_fields.get(name) or RunOptions.model_fields[name]


def add_tiling_options(group, names: tuple[str, ...], notes: dict[str, str] | None = None) -> None:
    """An option ``--<field>`` for each named field of `TilingParams` or `RunOptions`
    (default None: the command applies the model's, or a setting's, at its edge). Its
    help is the field's description, then the command's ``notes`` on it, else the
    model's default."""
    notes = notes or {}
    for name in names:
        field = _tiling_field(name)
        ann = base_type(field.annotation)
        kwargs: dict = {"dest": name, "default": None}
        if typing.get_origin(ann) is typing.Literal:
            kwargs["choices"] = list(typing.get_args(ann))
        elif typing.get_origin(ann) is tuple:
            kwargs.update(type=_origin, metavar="X,Y")
        else:
            kwargs.update(type=ann, metavar=metavar(ann, field.description))
        note = notes.get(name, f"default {field.default}")
        kwargs["help"] = f"{field.description} ({note})".replace("%", "%%")
        group.add_argument("--" + name.replace("_", "-"), **kwargs)


def tiling_default(name: str):
    """The model's default of a `TilingParams` or `RunOptions` field."""
    return _tiling_field(name).default
