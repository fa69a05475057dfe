"""One module per ``vloc`` subcommand; :mod:`clients.cli` loads them on demand."""
