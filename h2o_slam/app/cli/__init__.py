"""Command-line tools: thin argparse shells over library functions."""
