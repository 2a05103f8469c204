from rfcl_sim import check


def test_installed_matrix_is_the_tested_one():
    assert check.check() == []


def test_a_wrong_version_is_reported(monkeypatch):
    monkeypatch.setitem(check.MATRIX, "numpy", (lambda v: False, "<0"))
    problems = check.check()
    assert len(problems) == 1 and problems[0].startswith("numpy: ") and "expected <0" in problems[0]
