"""The on-board catalog: stars, pair table and its indices, and the glue to the binary catalog image."""
