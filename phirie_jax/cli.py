"""The ``phirie`` command.

Subcommands are plain functions; tyro turns their typed, documented arguments into
the command line (and nested config dataclasses into ``--stage.field`` options), so
the CLI, the configs and their documentation never drift apart.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import tyro

from phirie_jax.errors import SceneInputError

Scene = Annotated[Path, tyro.conf.Positional]


def info(scene: Scene, gaussians: Path | None = None, surface: Path | None = None,
         json_out: Annotated[bool, tyro.conf.arg(name="json")] = False) -> None:
    """Report what a scene folder (or a Gaussian PLY) holds: layout, Gaussians, cameras,
    images, surface mesh, masks, candidates and scene bounds.

    Args:
        scene: a scene folder (COLMAP, nerfstudio or ScanNet++ layout) or a Gaussian PLY.
        gaussians: Gaussian PLY to use instead of the one found in the folder.
        surface: surface mesh to use instead of the one found in the folder.
        json_out: print the facts as JSON instead of a table.
    """
    from phirie_jax.info import scene_facts
    from phirie_jax.io.scene import load_scene

    facts = scene_facts(load_scene(scene, gaussians=gaussians, surface=surface))
    if json_out:
        print(json.dumps(facts, indent=2))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"phirie info: {facts['root']}", show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value")
    for key, value in facts.items():
        if key == "root":
            continue
        if isinstance(value, dict):
            value = "\n".join(f"{k}: {v}" for k, v in value.items())
        table.add_row(key, "—" if value is None else str(value))
    Console().print(table)


COMMANDS = {"info": info}


def main(argv: list[str] | None = None) -> int:
    try:
        tyro.extras.subcommand_cli_from_dict(
            COMMANDS, prog="phirie", args=argv,
            description="Turn a 3D Gaussian Splatting capture into an interactive simulation scene.",
        )
    except SceneInputError as err:
        print(f"phirie: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("phirie: interrupted", file=sys.stderr)
        return 130
    return 0


def entry_point() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entry_point()
