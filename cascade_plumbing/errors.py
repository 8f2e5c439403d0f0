"""The one way a script stops on bad input or a failed operation: one line, non-zero exit."""


def fail(message: str) -> None:
    """Stop with a one-line error and a non-zero exit code."""
    raise SystemExit(f"error: {message}")
