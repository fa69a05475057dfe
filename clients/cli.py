"""The ``vloc`` command line: one entry point, one module per subcommand.

Subcommands are imported only when invoked, so ``vloc --help`` stays fast and a command's
heavy dependencies (OpenCV, uvicorn, matplotlib) load only for the commands that need them.
"""

from __future__ import annotations

import importlib

import click

# name -> (module, attribute, one-line help)
COMMANDS: dict[str, tuple[str, str, str]] = {
    "eval": ("vloc.clients.commands.eval", "eval_cmd",
             "Run the localisers over a dataset offline and print the error/speed table."),
    "serve": ("vloc.clients.commands.serve", "serve_cmd", "Run the API server (uvicorn) with settings from the environment."),
    "world": ("vloc.clients.commands.world", "world_cmd", "Generate a synthetic world: a route rendered under several illuminations, as a dataset folder."),
    "map": ("vloc.clients.commands.map", "map_group",
            "Maps: create, list, show, delete, import a folder of images, build."),
    "localize": ("vloc.clients.commands.localize", "localize_cmd",
                 "Where was each image taken? One answer per image, nothing stored."),
    "session": ("vloc.clients.commands.session", "session_group",
                "Sessions: create, show, delete, reset, initial pose, send frames, watch poses."),
    "mavlink": ("vloc.clients.commands.mavlink", "mavlink_cmd",
                "A MAVLink autopilot: camera frames to a session, its poses back as GPS_INPUT."),
    "replay": ("vloc.clients.commands.replay", "replay_cmd",
               "Simulated devices: play a dataset into a running server, print the error table."),
    "navigate": ("vloc.clients.commands.navigate", "navigate_cmd",
                 "Teach a route in the robot world and repeat it through the service (Li et al.)."),
    "demo": ("vloc.clients.commands.demo", "demo_cmd",
             "The whole product in one command: synthetic world, server, map, device replay, table."),
}


class LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in COMMANDS:
            return None
        module, attr, _ = COMMANDS[cmd_name]
        return getattr(importlib.import_module(module), attr)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = [(name, COMMANDS[name][2]) for name in self.list_commands(ctx)]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="vloc")
def main() -> None:
    """vloc: visual localisation from a map of GPS-tagged images."""


if __name__ == "__main__":
    main()
