"""The project documents itself inside the repository (issue 14): no link leaves it."""

from __future__ import annotations

import re

import pytest

from supervisor.paths import REPO_ROOT

DOCS = ["README.md", "docs/method.md", "docs/architecture.md", "docs/operation.md", "docs/tuning.md"]


@pytest.mark.parametrize("doc", DOCS)
def test_local_links_resolve_inside_the_repository(doc):
    text = (REPO_ROOT / doc).read_text(encoding="utf-8")
    assert "../shared" not in text
    base = (REPO_ROOT / doc).parent
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if re.match(r"^[a-z]+:", target):
            continue
        path = (base / target).resolve()
        assert REPO_ROOT.resolve() in [path, *path.parents], f"{doc} links outside the repository: {target}"
        assert path.exists(), f"{doc} links to a missing file: {target}"


def test_method_cites_both_papers_and_says_what_is_beyond_them():
    text = (REPO_ROOT / "docs/method.md").read_text(encoding="utf-8")
    assert "Forward Prediction of Target Localization Failure" in text
    assert "Learnable Viewpoint Evolution" in text
    assert "## 7. Beyond the papers" in text and "f(theta; alpha, K, mu)" in text


def test_code_refers_to_the_documentation_in_the_repository():
    for path in (REPO_ROOT / "supervisor").rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        for m in re.finditer(r"(\S*)METHOD\.md", text):
            pytest.fail(f"{path.relative_to(REPO_ROOT)} refers to {m.group(0)}, which users do not have")
