"""One module per ``usdface`` sub-command (thin: parse arguments, call the API, print)."""

NAME_MAP_HELP = ('JSON object {"studio_channel": "arkitName"} or two-column CSV mapping the avatar\'s '
                 "channel names to ARKit names, for names usdface does not recognise (see docs/names.md)")


def add_name_map_option(p) -> None:
    """``--name-map FILE`` for every command that reads an avatar."""
    p.add_argument("--name-map", metavar="FILE", help=NAME_MAP_HELP)
