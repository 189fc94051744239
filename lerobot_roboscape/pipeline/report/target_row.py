"""A target row: what every target of the project's reports is ({"value", "goal", "met"} and, where it helps,
"detail"), written to results.json and rendered in the reports' tables."""


def target_row(value, goal: str, met: bool, detail: str | None = None) -> dict:
    """A target row: the measured value, the goal, whether it is met, and what the value is made of (optional)."""
    row = {"value": None if value is None else round(float(value), 4), "goal": goal, "met": bool(met)}
    return row | ({"detail": detail} if detail else {})
