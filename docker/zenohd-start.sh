#!/bin/sh
# The router's start (docker/compose.router.yaml), in the eclipse/zenoh image (busybox sh).
#
# zenohd takes its login to the machine from its config file only, and the image's
# /entrypoint.sh passes its arguments on unquoted and echoes them. So the password goes into a
# copy of the config in a tmpfs (owner-only), written with shell built-ins (no command line
# carries it), and zenohd gets two plain arguments: `-c /run/zenohd/zenohd.json5`.
set -eu

CONFIG=/etc/zenoh/zenohd.json5
RUN_DIR=/run/zenohd
PASSWORD_FILE=/run/secrets/machine.password
PLACEHOLDER=@MACHINE_PASSWORD@

password=$(cat "$PASSWORD_FILE")
case $password in
    "" | *[!A-Za-z0-9_-]*)
        echo "zenohd-start: $PASSWORD_FILE must hold one word of A-Z a-z 0-9 _ - (machine credentials init makes it so)" >&2
        exit 2
        ;;
esac
if ! grep -q "$PLACEHOLDER" "$CONFIG"; then
    echo "zenohd-start: $CONFIG has no $PLACEHOLDER for the machine login" >&2
    exit 2
fi

umask 077
mkdir -p "$RUN_DIR"
while IFS= read -r line || [ -n "$line" ]; do
    case $line in
        *"$PLACEHOLDER"*) line="${line%%"$PLACEHOLDER"*}$password${line#*"$PLACEHOLDER"}" ;;
    esac
    printf '%s\n' "$line"
done < "$CONFIG" > "$RUN_DIR/zenohd.json5"

exec /entrypoint.sh -c "$RUN_DIR/zenohd.json5"
