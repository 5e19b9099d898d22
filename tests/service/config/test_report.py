"""A report cut to size: errors first, and a count of what was left out."""

from __future__ import annotations

from ride_machine.schema.findings import Severity
from ride_machine.service.config.report import Category, at_most, error, findings_of, warning


def test_a_capped_report_keeps_its_errors_first_and_its_verdict() -> None:
    found = [warning(Category.BUS, f"/w{i}", "w") for i in range(150)]
    found.append(error(Category.TIMEOUT, "/e", "e"))
    report = at_most(findings_of(found), 100)
    assert not report.ok and len(report.findings) == 101
    assert report.findings[0].path == "/e"
    more = report.findings[-1]
    assert (more.category, more.severity, more.extra) == ("more", Severity.WARNING, {"more": 51})
    assert "51 more findings" in more.message


def test_a_report_within_the_cap_is_left_as_it_is() -> None:
    report = findings_of([warning(Category.BUS, "/w", "w")])
    assert at_most(report, 1) is report
