"""Road slope: paper 004's prediction model + cubic observer, the classical contrast, auto selection."""
