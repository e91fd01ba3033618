"""What every `hil` subcommand's parser shares: the help formatter (examples kept as written,
every option's default shown once) and the subcommand parser whose help ends with examples."""

from __future__ import annotations

import argparse


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the examples' layout and shows every option's default (where it has one), once."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (
            "%(default)" not in text
            and "(default" not in text  # the text states it already
            and all(default is not no for no in (None, False, argparse.SUPPRESS))  # 0 is shown
            and default != []  # a repeatable option given no times
            and action.option_strings
        ):
            text += " (default: %(default)s)"
        return text


def example_parser(
    commands: argparse._SubParsersAction, name: str, help_text: str, examples: str
) -> argparse.ArgumentParser:
    """A subcommand parser whose help ends with examples."""
    parser = commands.add_parser(
        name,
        help=help_text,
        description=help_text,
        epilog="examples:\n" + examples,
        formatter_class=HelpFormatter,
    )
    parser.set_defaults(command_parser=parser)  # the deepest command's, for its usage errors
    return parser
