"""mkdocs hook: the pages name files outside docs/ by their path in the repository
(``../benchmarks/README.md``), so that the links also work where docs/ is read as plain Markdown, on
GitHub for instance. This adds every such file to the site, under ``repo/``, so that the links
resolve in the built site and ``mkdocs build --strict`` checks them like any other link."""

from __future__ import annotations

import os
import posixpath
import re
from pathlib import Path

from mkdocs.structure.files import File, Files, InclusionLevel

LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)\s]*)?\)")


def _dest(rel: str, directory_urls: bool) -> str:
    """Where the repository file ``rel`` (a path from the repository root) lands in the site: under
    ``repo/``, a Markdown file as a page (``README.md`` as its folder's index)."""
    if not rel.endswith(".md"):
        return "repo/" + rel
    folder, name = posixpath.split(rel[:-3])
    if name in ("README", "index"):
        return posixpath.join("repo", folder, "index.html")
    return posixpath.join("repo", folder, name, "index.html") if directory_urls else posixpath.join("repo", folder, name + ".html")


def on_files(files: Files, config) -> Files:
    """mkdocs' ``on_files`` event: the site's files plus every repository file a page links to.

    Arguments:
        files: the files mkdocs found in docs/. config: the loaded mkdocs.yml.

    Returns:
        ``files``, with the linked repository files added (Markdown ones as pages, whose own links
        are followed too). A link to a file that does not exist is left alone: mkdocs reports it.
    """
    docs = Path(config["docs_dir"])
    repo = os.path.normpath(docs.parent)
    todo = list(files.documentation_pages())
    while todo:
        page = todo.pop()
        here = posixpath.dirname(page.src_uri)
        for target in LINK.findall(Path(page.abs_src_path).read_text(encoding="utf-8")):
            if re.match(r"^[a-z]+:", target):
                continue
            uri = posixpath.normpath(posixpath.join(here, target))
            if not uri.startswith("../") or files.get_file_from_path(uri) is not None:
                continue
            path = os.path.normpath(os.path.join(docs, uri))
            if not os.path.isfile(path) or os.path.commonpath([path, repo]) != repo:
                continue  # left to mkdocs, which reports the link as broken
            rel = Path(path).relative_to(repo).as_posix()
            new = File(uri, src_dir=str(docs), dest_dir=config["site_dir"],
                       use_directory_urls=config["use_directory_urls"],
                       dest_uri=_dest(rel, config["use_directory_urls"]),
                       # set, since the default exclusion of hidden files would take '../' for one
                       inclusion=InclusionLevel.INCLUDED)
            files.append(new)
            if new.is_documentation_page():
                todo.append(new)
    return files
