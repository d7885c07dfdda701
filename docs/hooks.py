"""mkdocs hooks (mkdocs.yml ``hooks``): the committed result pages that docs/ links to join the
site, so that the links hold there as they do in the repository.

``docs/results.md`` links ``../results/paper/README.md`` and the like (files outside
``docs/``). The Markdown and figures of ``results/paper`` and ``results/reduced`` are added to
the site at ``results/...`` and those links rewritten to point there; a link to a file that does
not exist still fails the strict build.
"""

from pathlib import Path

from mkdocs.structure.files import File

ROOT = Path(__file__).resolve().parents[1]
INCLUDED = ("results/paper", "results/reduced")
SUFFIXES = (".md", ".png")


def on_files(files, config):
    for folder in INCLUDED:
        for path in sorted((ROOT / folder).glob("*")):
            if path.is_file() and path.suffix in SUFFIXES:
                files.append(File(path.relative_to(ROOT).as_posix(), str(ROOT),
                                  config["site_dir"], config["use_directory_urls"]))
    return files


def on_page_markdown(markdown, page, config, files):
    depth = page.file.src_uri.count("/")
    if page.file.src_uri.startswith(INCLUDED):
        return markdown
    outside, inside = "../" * (depth + 1), "../" * depth
    for folder in INCLUDED:
        markdown = markdown.replace(f"]({outside}{folder}/", f"]({inside}{folder}/")
    return markdown
