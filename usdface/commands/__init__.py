"""One module per ``usdface`` sub-command (thin: parse arguments, call the API, print)."""
