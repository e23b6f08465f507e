"""The processes of derl: the `derl` command line, the bus nodes and the tools around them."""
