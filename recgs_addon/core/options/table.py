"""The declaration of an option (see the package's docstring)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Optional

#: ``Setting.default`` when the sidebar's default is the command line's.
SAME = object()


@dataclass(frozen=True)
class Setting:
    """How the sidebar shows an option: its label and range, and its default where that differs
    from the command line's (``why`` then says why; the tooltip ends with it)."""
    label: str
    default: Any = SAME
    why: str = ""
    minimum: Optional[float] = None
    maximum: Optional[float] = None
    soft_max: Optional[float] = None
    step: Optional[int] = None
    #: the setting's kind where it is not the option's: "int" for a number that the command line
    #: takes as text ("auto" or a number)
    kind: str = ""


@dataclass(frozen=True)
class Option:
    """One command-line option (``flag``: ``--name``, or a positional's name)."""
    flag: str
    help: str
    #: argparse's ``type`` (None: text); ``bool`` is an on/off flag (``store_true``)
    type: Optional[Callable] = None
    default: Any = None
    #: the values it takes, each with the sidebar's label and a description
    #: (``(value, label, description)``) or the value alone (command line only)
    choices: tuple = ()
    #: said on the command line only, after ``help`` (what concerns the command line alone)
    note: str = ""
    group: str = ""
    #: options of one name here exclude each other on the command line
    exclusive: str = ""
    required: bool = False
    metavar: Optional[str] = None
    setting: Optional[Setting] = None

    @property
    def dest(self) -> str:
        return self.flag.lstrip("-").replace("-", "_")

    @property
    def values(self) -> tuple:
        return tuple(c[0] if isinstance(c, tuple) else c for c in self.choices)

    def cli_help(self) -> str:
        """The command line's help: the help, the default (unless the help says it), each
        labelled choice's description, and the note."""
        text = self.help
        if self.default is not None and self.type is not bool and "(default" not in text:
            text += f" (default {self.default})"
        if self.choices and isinstance(self.choices[0], tuple):
            text += ". " + "; ".join(f"{v}: {d}" for v, _, d in self.choices)
        return f"{text}. {self.note}" if self.note else text

    def add_to(self, parser) -> None:
        """Add the option to an argparse parser (or argument group)."""
        kw: dict = {"help": self.cli_help()}
        if self.type is bool:
            kw["action"] = "store_true"
        else:
            if self.type is not None:
                kw["type"] = self.type
            if self.choices:
                kw["choices"] = self.values
            if self.metavar:
                kw["metavar"] = self.metavar
            if self.flag.startswith("-"):
                kw["default"] = self.default
        if self.required:
            kw["required"] = True
        parser.add_argument(self.flag, **kw)

    def setting_help(self) -> str:
        """The sidebar's tooltip: the help, and what the setting's own default or values mean."""
        return f"{self.help}. {self.setting.why}" if self.setting is not None and self.setting.why else self.help

    def setting_default(self):
        """The sidebar's default (the command line's unless the setting says otherwise)."""
        return self.default if self.setting is None or self.setting.default is SAME else self.setting.default


@dataclass
class OptionTable:
    """Options in the order the command line lists them, by ``dest``."""
    options: list = field(default_factory=list)

    def __post_init__(self) -> None:
        dests = [o.dest for o in self.options]
        dup = {d for d in dests if dests.count(d) > 1}
        if dup:
            raise ValueError(f"options declared twice: {sorted(dup)}")
        self.by_dest = {o.dest: o for o in self.options}

    def __getitem__(self, dest: str) -> Option:
        return self.by_dest[dest]

    def __iter__(self):
        return iter(self.options)

    def settings(self) -> list:
        """The options the sidebar shows."""
        return [o for o in self.options if o.setting is not None]

    def add_to(self, parser) -> None:
        """Every option to an argparse parser, those of a ``group`` in an argument group and those
        of an ``exclusive`` set in a mutually exclusive group."""
        groups: dict = {}
        for opt in self.options:
            target = parser
            if opt.group:
                if opt.group not in groups:
                    groups[opt.group] = parser.add_argument_group(opt.group)
                target = groups[opt.group]
            if opt.exclusive:
                key = ("exclusive", opt.exclusive)
                if key not in groups:
                    groups[key] = target.add_mutually_exclusive_group()
                target = groups[key]
            opt.add_to(target)
