"""What every layer may use: the error types, atomic files, worker pools."""
