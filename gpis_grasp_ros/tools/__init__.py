"""Command line and its commands (demo, make-bag, benchmark, bench). May import anything."""
