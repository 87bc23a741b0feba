"""mkdocs hook: the notebooks (../notebooks/*.ipynb) and the changelog (../CHANGELOG.md) join the
site's files as they are stored in the repository, so that docs/ holds no copies; mkdocs-jupyter
renders the notebooks as stored (the test suite executes them, not the site build)."""

from pathlib import Path

from mkdocs.plugins import event_priority
from mkdocs.structure.files import File


@event_priority(100)  # before mkdocs-jupyter looks at the files
def on_files(files, config):
    root = Path(config["config_file_path"]).parent
    # files of the repository root (not generated ones: mkdocs-jupyter reads a notebook by its path)
    paths = [f"notebooks/{nb.name}" for nb in sorted((root / "notebooks").glob("*.ipynb"))] + ["CHANGELOG.md"]
    for path in paths:
        files.append(File(path, str(root), config["site_dir"], config["use_directory_urls"]))
    return files
