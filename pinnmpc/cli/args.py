"""The command line before Hydra composes: unknown group options and misspelt settings end in one line, and the
config dirs a command line adds travel into printed resume commands."""

from __future__ import annotations

import dataclasses
import re
import sys
from pathlib import Path

from pinnmpc.util.paths import CONF

EXIT_BAD_INPUT = 2  # exit code for bad input
CHOICE = re.compile(r"^\+{0,2}([a-z_]+)=([A-Za-z0-9_.-]+)$")  # a plain `group=option` override (no sweeps)


def config_dir_args(argv: list[str] | None = None) -> list[str]:
    """The command line's config-dir arguments (--config-dir as an absolute path, hydra.searchpath as given), so a
    printed resume command finds the same configs."""
    out, it = [], iter(sys.argv[1:] if argv is None else argv)
    for arg in it:
        if arg in ("--config-dir", "-cd"):
            out += ["--config-dir", str(Path(next(it, "")).resolve())]
        elif arg.startswith(("--config-dir=", "-cd=")):
            out += ["--config-dir", str(Path(arg.split("=", 1)[1]).resolve())]
        elif arg.lstrip("+").startswith("hydra.searchpath="):
            out.append(arg)
    return out


def _config_dirs(argv: list[str]) -> list[Path] | None:
    """conf/ and the dirs a command line adds (--config-dir, -cd, hydra.searchpath); None where one is not a plain
    folder (e.g. pkg://), so that no option is refused that Hydra might still find."""
    dirs, it = [CONF], iter(config_dir_args(argv))
    for arg in it:
        if arg == "--config-dir":
            dirs.append(Path(next(it)))
            continue
        for entry in arg.split("=", 1)[1].strip("[]").split(","):  # hydra.searchpath=[...]
            entry = entry.strip().strip("'\"")
            if entry.startswith("pkg://"):
                return None
            dirs.append(Path(entry.removeprefix("file://")))
    return dirs


KEY = re.compile(r"^([A-Za-z_][A-Za-z0-9_-]*)(?:\.[^=]*)?=")  # a `key=...` or `key.sub=...` override


def _top_keys(name: str) -> set[str] | None:
    """The top-level keys conf/<name>.yaml composes to: its own, its groups' and those of the configs it extends
    (None where the files do not tell, so that nothing is refused that Hydra might accept)."""
    from omegaconf import OmegaConf

    path = CONF / f"{name}.yaml"
    if not path.is_file():
        return None
    raw = OmegaConf.load(path)
    keys = {str(k) for k in raw if k != "defaults"} | {"hydra"}
    for entry in raw.get("defaults") or []:
        if isinstance(entry, str):
            sub = set() if entry == "_self_" else _top_keys(entry)
            if sub is None:
                return None
            keys |= sub
            continue
        for k in entry:  # {group: option}, {"optional group@package": option}, {"override hydra/help": option}
            group, _, package = str(k).removeprefix("optional ").removeprefix("override ").strip().partition("@")
            keys.add((package or group).replace("/", ".").split(".")[0])
    return keys


def check_keys(prog: str, args: list[str]) -> None:
    """A misspelt setting (`controler=casadi`) ends in one line naming it and the settings there are (Hydra's own
    message suggests `+controler=...`, which would run, silently ignoring it)."""
    keys = _top_keys(prog.rsplit(".", 1)[-1])
    if keys is None:
        return
    for arg in args:
        match = None if arg.startswith(("+", "~", "-")) else KEY.match(arg)
        if match is not None and match[1] not in keys:
            have = sorted(keys - {"hydra"})
            print(f"{prog}: error: unknown setting {match[1]!r} ({arg}); expected one of {have}", file=sys.stderr)
            sys.exit(EXIT_BAD_INPUT)


TYPED = re.compile(r"^\+{0,2}controller\.solvers\.([A-Za-z_]+)\.([A-Za-z_]+)=")  # a solver setting
STRUCTURED_KEY = re.compile(r"^\+{0,2}(plant|module|data)\.([A-Za-z_]+)=")  # a setting of a structured config


def _values(arg: str) -> list[object]:
    """The value(s) an override sets, as Hydra parses them (a sweep's every value); [] where Hydra cannot parse
    it (Hydra's own error follows) or a value is an interpolation (checked when it resolves)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        override = OverridesParser.create().parse_overrides([arg])[0]
        values = list(override.sweep_iterator()) if override.is_sweep_override() else [override.value()]
    except Exception:  # noqa: BLE001  (Hydra's grammar errors have several types; Hydra reports them itself)
        return []
    return [v for v in values if not (isinstance(v, str) and "${" in v)]


def check_typed(prog: str, args: list[str]) -> None:
    """A solver setting (`controller.solvers.<name>.<field>=value`, a structured config) that names no field of
    that solver, or a value its type or range refuses, ends in one line before Hydra composes (Hydra's own message
    is several lines); in a sweep, before any job runs."""
    typed = [(arg, match) for arg in args if (match := TYPED.match(arg)) is not None]
    if not typed:
        return
    from pinnmpc.controller.solvers import SOLVERS, make_solver  # only now: torch loads with the solvers

    for arg, match in typed:
        name, key = match[1], match[2]
        setting = arg.split("=", 1)[0].lstrip("+")
        if name not in SOLVERS:
            _refuse(prog, f"{setting}: no solver {name!r}; expected one of {sorted(SOLVERS)}")
        fields = [f.name for f in dataclasses.fields(SOLVERS[name])]
        if key not in fields:
            _refuse(prog, f"unknown setting {setting!r}; expected one of {fields} (the fields of {name})")
        for value in _values(arg):
            try:
                make_solver(name, **{key: tuple(value) if isinstance(value, list) else value})
            except ValueError as e:
                said = str(e)
                _refuse(prog, f"{setting}={value!r}: {said[said.find('expected') :] if 'expected' in said else said}")


def _default_choice(name: str, group: str) -> str | None:
    """The option conf/<name>.yaml's defaults list picks for a group (following the configs it extends)."""
    from omegaconf import OmegaConf

    path = CONF / f"{name}.yaml"
    if not path.is_file():
        return None
    for entry in OmegaConf.load(path).get("defaults") or []:
        if isinstance(entry, str):
            found = None if entry == "_self_" else _default_choice(entry, group)
            if found:
                return found
        elif group in entry:
            return str(entry[group])
    return None


def _options(group: str) -> dict[str, type]:
    """The structured configs of a group by option: plant=scipy|mujoco, module=pinn, data=collocation."""
    if group == "plant":
        from pinnmpc.plant.settings import PLANTS

        return dict(PLANTS)
    from pinnmpc.training.settings import SECTIONS

    return SECTIONS[group]


def check_structured(prog: str, args: list[str]) -> None:
    """A setting of a structured config group (`plant.<field>=value`, `module.<field>=value`, `data.<field>=value`)
    that names no field of the chosen option, or a value its type or range refuses, ends in one line before Hydra
    composes; in a sweep before any job runs."""
    config = prog.rsplit(".", 1)[-1]
    for arg in args:
        match = STRUCTURED_KEY.match(arg)
        if match is None:
            continue
        group, key = match[1], match[2]
        options = _options(group)
        chosen = [m[2] for m in map(CHOICE.match, args) if m is not None and m[1] == group]
        option = chosen[-1] if chosen else _default_choice(config, group) or ("scipy" if group == "plant" else None)
        if option not in options:
            continue  # no such group in this command, or an option of a user's config dir: Hydra checks it
        cls = options[option]
        names = [f.name for f in dataclasses.fields(cls)]
        if key not in names:
            other = [k for k, c in options.items() if key in {f.name for f in dataclasses.fields(c)}]
            hint = f" (a setting of {group}={other[0]}: add {group}={other[0]})" if other else ""
            _refuse(prog, f"unknown setting '{group}.{key}' of {group}={option}; expected one of {names}{hint}")
        for value in _values(arg):
            try:
                cls(**{key: value})
            except ValueError as e:
                _refuse(prog, str(e))


def _refuse(prog: str, message: str) -> None:
    """One line on stderr and the bad-input exit code."""
    print(f"{prog}: error: {message}", file=sys.stderr)
    sys.exit(EXIT_BAD_INPUT)


def help_text(prog: str) -> str | None:
    """The command's --help page from conf/hydra/help/<command>.yaml (None where it has none), rendered as Hydra
    renders a template that lists no config groups, without the seconds Hydra spends listing them anyway."""
    from omegaconf import OmegaConf

    path = CONF / "hydra" / "help" / f"{prog.rsplit('.', 1)[-1]}.yaml"
    if not path.is_file():
        return None
    page = OmegaConf.create({"hydra": {"help": OmegaConf.load(path)}})
    return str(page.hydra.help.template)


def check_choices(prog: str, argv: list[str] | None = None) -> None:
    """What every command runs before Hydra composes: --help prints the command's page and exits; a `group=option`
    override whose group/option.yaml exists in no config dir (conf/, --config-dir, hydra.searchpath) ends the
    process with one line naming it and the options there (Hydra's own message is a multi-line search-path dump);
    then the structured configs are registered for Hydra to compose with."""
    from pinnmpc.cli.structured import register_configs

    _check_command_line(prog, sys.argv[1:] if argv is None else argv)
    register_configs()


def _check_command_line(prog: str, args: list[str]) -> None:
    """check_choices' checks of the command line, in the order that answers --help before anything else."""
    dirs = _config_dirs(args)
    if dirs is not None and len(dirs) == 1 and ("--help" in args or "-h" in args) and help_text(prog) is not None:
        print(help_text(prog))
        sys.exit(0)
    check_grammar(prog, args)
    if dirs is None:
        return
    if len(dirs) == 1:  # a user's config dir may hold another primary config: its keys are not known here
        check_keys(prog, args)
    check_typed(prog, args)
    check_structured(prog, args)
    for arg in args:
        match = CHOICE.match(arg)
        if match is None or not any((d / match[1]).is_dir() for d in dirs):
            continue
        group, option = match[1], match[2]
        if not any((d / group / f"{option}.yaml").is_file() for d in dirs):
            have = sorted({f.stem for d in dirs for f in (d / group).glob("*.yaml")})
            where = "conf" if len(dirs) == 1 else "any config dir"
            print(f"{prog}: error: {group}={option!r}: no {group}/{option}.yaml in {where}; expected one of {have}",
                  file=sys.stderr)  # fmt: skip
            sys.exit(EXIT_BAD_INPUT)


GRAMMAR_NOISE = ("See https://", "Error parsing override")  # Hydra's lines that say nothing about this override
LEXER = "LexerNoViableAltException: "  # Hydra's lexer error: the override, then a caret under the bad character


def _overrides(args: list[str]) -> list[str]:
    """The command line's overrides as Hydra's own argument parser finds them (none where it refuses the line: Hydra
    then says why itself)."""
    import argparse
    import contextlib
    import io

    from hydra._internal.utils import get_args_parser

    if "--version" in args:
        return []
    parser = get_args_parser()
    parser.exit_on_error = False
    try:
        with contextlib.redirect_stderr(io.StringIO()):
            return list(parser.parse_intermixed_args(args).overrides or [])
    except (argparse.ArgumentError, SystemExit, TypeError):
        return []


def grammar_error(arg: str) -> str | None:
    """Why Hydra's override grammar refuses arg, in a few words (None: it parses)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        OverridesParser.create().parse_overrides([arg])
    except (HydraException, ValueError) as e:
        lines = [line for line in str(e).splitlines() if line.strip() and not line.startswith(GRAMMAR_NOISE)]
        if len(lines) >= 2 and lines[0].startswith(LEXER) and "^" in lines[1]:
            at = lines[1].index("^") - len(LEXER)
            if 0 <= at < len(arg):
                return f"unexpected {arg[at]!r} at character {at + 1}"
        return lines[0].removeprefix(LEXER) if lines else type(e).__name__
    return None


def check_grammar(prog: str, args: list[str]) -> None:
    """An override Hydra's grammar cannot parse (`reference.name=it's`, `x0=[0.1,0`) ends in one line naming it and
    how to write it, exit 2 (Hydra's own message is several lines and exits 1)."""
    from pinnmpc.util.commands import hydra_quote

    for arg in _overrides(args):
        why = grammar_error(arg)
        if why is None:
            continue
        key, eq, value = arg.partition("=")
        if not eq:
            hint = "expected key=value"
        elif value.lstrip().startswith(("[", "{")):
            hint = "expected a list as [a,b,...] or a mapping as {k:v}, every bracket closed"
        else:
            quoted = f"{key}={hydra_quote(value)}"
            hint = (
                f"expected Hydra's override grammar: quote a value with quotes, brackets, commas or '=', e.g. {quoted}"
            )
        _refuse(prog, f"cannot parse the override {arg!r} ({why}); {hint} (docs/troubleshooting.md)")
