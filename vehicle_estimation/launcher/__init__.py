"""Starting the node processes, live or against a bag (the lock-step player), and planning what each node does."""
