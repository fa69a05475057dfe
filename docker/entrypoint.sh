#!/bin/sh
# Run the command as the image's user (vloc, uid 10001). Started as root (the default), it
# first gives that user the data directory when it cannot write there: a host folder
# bind-mounted at /data belongs to the host's user. Started as another user
# (`docker run --user`), it runs the command as that user unchanged.
set -eu
data="${VLOC_DATA_DIR:-/data}"
if [ "$(id -u)" = "0" ]; then
    mkdir -p "$data"
    if ! setpriv --reuid=vloc --regid=vloc --init-groups test -w "$data"; then
        chown -R vloc:vloc "$data"
    fi
    exec setpriv --reuid=vloc --regid=vloc --init-groups "$@"
fi
exec "$@"
