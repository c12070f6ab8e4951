"""One module per paper reproduction, named after the paper number in ../shared/papers/README.md."""
