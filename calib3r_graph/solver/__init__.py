"""The solver: from predictions to the joint factor graph (observations, init, graph), its solve, the
uncertainty and systematic-error estimates, the jackknife check and next-best-pose planning (plan).

Above io (and factors), below evaluation, the report and the CLI."""
