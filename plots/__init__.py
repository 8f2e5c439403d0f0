"""The paper's figures and tables from our own runs: `python plots/<script>.py --help` (see docs/reproducing.md)."""
