"""``schlieren params``: every run parameter with its meaning, unit, default and valid values.

The default output is a commented YAML file that ``schlieren run --params`` accepts;
``--format markdown`` prints docs/parameters.md. Both come from the parameter schema
(:mod:`schlieren.pipeline.params`), which also validates ``--params``.
"""

from __future__ import annotations

import sys


def add_parser(sub) -> None:
    p = sub.add_parser("params", help="print every run parameter: meaning, unit, default, valid values",
                       description="Prints every parameter of every stage with its meaning, unit, default and "
                                   "valid values, as a commented YAML file. Save it, keep what you change and "
                                   "pass it to `schlieren run --params FILE`; unknown names, wrong types and "
                                   "values out of range are refused before any work.")
    p.add_argument("--out", default=None, help="write to this file instead of standard output")
    p.add_argument("--format", default="yaml", choices=["yaml", "markdown"],
                   help="yaml (for --params, default) or markdown (docs/parameters.md)")
    p.set_defaults(func=handler)


def handler(args) -> int:
    from schlieren.pipeline.params_text import params_markdown, params_yaml
    from schlieren.pipeline.stages import RunConfig

    text = params_markdown(RunConfig) if args.format == "markdown" else params_yaml(RunConfig)
    if args.out:
        from schlieren.storage.params_io import write_params_text

        write_params_text(args.out, text)
        print(args.out)
    else:
        sys.stdout.write(text)
    return 0
