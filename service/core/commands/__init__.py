"""What a command is held to: its timecode, who asked, at most once, its completion."""
