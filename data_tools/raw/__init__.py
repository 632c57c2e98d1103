"""RAW focal stacks -> training triples (``python -m data_tools.raw``): decode, align, fuse, depth from focus."""
