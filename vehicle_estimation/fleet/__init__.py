"""Fleet-scale replay: many bags, in parallel, on a distributed engine (``batch``)."""
