"""A fit's problem: model, evaluator, objective, bounds and clock over unconstrained z; free light powers."""
