"""The `repnet` command: serve, lift, plot, formats, adapt."""
