"""Built-in encoders and the contract third-party encoders implement."""
