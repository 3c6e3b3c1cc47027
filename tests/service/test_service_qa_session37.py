"""Session 37: the offline API docs' vendored assets come without source-map comments (the package ships no .map
files, so browsers' developer tools asked for one and logged a 404)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.api.routes.ui import _SOURCE_MAP_LINE


@pytest.fixture
def client(server: tuple[str, Path]) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server[0], timeout=30) as c:
        yield c


@pytest.mark.parametrize("asset, media", [("swagger-ui.css", "text/css"), ("redoc.standalone.js", "javascript"),
                                          ("swagger-ui-bundle.js", "javascript")])
def test_vendored_docs_assets_name_no_missing_source_map(client: httpx.Client, asset: str, media: str) -> None:
    r = client.get(f"/ui/vendor/{asset}")
    assert r.status_code == 200 and media in r.headers["content-type"]
    assert b"sourceMappingURL=" not in r.content.split(b"\n")[-1]
    assert not _SOURCE_MAP_LINE.search(r.content)
    assert int(r.headers["content-length"]) == len(r.content) > 10_000  # the asset itself, only the comment gone
    assert r.headers.get("etag")
    again = client.get(f"/ui/vendor/{asset}", headers={"If-None-Match": r.headers["etag"]})
    assert again.status_code == 304  # browsers' caching still works
    assert client.get(f"/ui/vendor/{asset}.map").status_code == 404


def test_source_map_comment_lines_only_are_removed() -> None:
    css = b"a{b:c}\n/*# sourceMappingURL=swagger-ui.css.map*/"
    js = b"var s = 'x //# sourceMappingURL=inside.a.string';\n//# sourceMappingURL=redoc.standalone.js.map\n"
    assert _SOURCE_MAP_LINE.sub(b"", css) == b"a{b:c}\n"
    assert _SOURCE_MAP_LINE.sub(b"", js) == b"var s = 'x //# sourceMappingURL=inside.a.string';\n"
