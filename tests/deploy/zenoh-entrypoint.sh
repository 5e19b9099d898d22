#!/bin/sh
# A replica of the published eclipse/zenoh image's /entrypoint.sh: its two lines as they are,
# arguments unquoted (split at every space) and echoed to the log. $BINARY is the path of the
# zenohd to run without its leading slash (the image sets BINARY=zenohd).
echo " * Starting: /$BINARY $@"
exec /$BINARY $@
