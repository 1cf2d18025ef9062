"""mkdocs hook: the benchmarks page gathers results/bench_*.md, each under its commit and date."""
import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MARKER = "<!-- results:"


def _stamp(path: Path) -> str:
    run = subprocess.run(["git", "log", "-1", "--format=%h %cs", "--", str(path.relative_to(ROOT))],
                         cwd=ROOT, capture_output=True, text=True)
    commit = run.stdout.strip() if run.returncode == 0 and run.stdout.strip() else "not committed"
    return f"*`{path.relative_to(ROOT)}`, commit {commit}*"


def _demoted(text: str) -> str:
    """Headings one level down; links relative to results/ made relative to the page."""
    text = re.sub(r"\]\((?!https?:|/|#)([^)]+)\)", r"](results/\1)", text)
    return "\n".join("#" + line if line.startswith("#") else line for line in text.splitlines())


def on_page_markdown(markdown, page, config, files):
    if page.file.src_uri != "benchmarks.md" or MARKER not in markdown:
        return markdown
    parts = [f"{_stamp(p)}\n\n{_demoted(p.read_text())}" for p in sorted((ROOT / "results").glob("bench_*.md"))]
    return markdown.split(MARKER)[0] + "\n\n".join(parts) + "\n"


def on_files(files, config):
    """The figures in results/ are served at results/... beside the pages."""
    from mkdocs.structure.files import File
    for png in sorted((ROOT / "results").rglob("*.png")):
        files.append(File(str(png.relative_to(ROOT)), str(ROOT), config["site_dir"], config["use_directory_urls"]))
    return files
