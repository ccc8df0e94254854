"""``schlieren params``: print every run parameter with its default, as a YAML file for ``--params``."""

from __future__ import annotations

import sys


def add_parser(sub) -> None:
    p = sub.add_parser("params", help="print the default run parameters (YAML for --params)",
                       description="Prints every parameter of every stage with its default value. "
                                   "Save it, edit what you need and pass it to `schlieren run --params FILE`; "
                                   "unknown names are refused.")
    p.add_argument("--out", default=None, help="write to this file instead of standard output")
    p.set_defaults(func=handler)


def handler(args) -> int:
    import yaml

    from schlieren.pipeline.stages import RunConfig, config_to_dict

    text = ("# schlieren run parameters (defaults); pass with: schlieren run SESSION --out STORE --params FILE\n"
            + yaml.safe_dump(config_to_dict(RunConfig()), sort_keys=False, default_flow_style=None))
    if args.out:
        from schlieren.storage.params_io import write_params_text

        write_params_text(args.out, text)
        print(args.out)
    else:
        sys.stdout.write(text)
    return 0
