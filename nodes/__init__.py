"""The processes of derl: the `derl` command line and, later, the bus nodes."""
