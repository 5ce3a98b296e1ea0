"""Scene XML text for the bad-input tests: a planar-180 sensor and what a test adds to it, written to a file."""

SENSOR = '<sensor type="lidar"><string name="pattern" value="planar-180"/></sensor>'


def scene_xml(body: str) -> str:
    """A scene of :data:`SENSOR` followed by ``body`` (XML elements)."""
    return f'<scene version="3.0.0">{SENSOR}{body}</scene>'


def write(tmp_path, text: str):
    """``tmp_path / "scene.xml"``, holding ``text``."""
    path = tmp_path / "scene.xml"
    path.write_text(text)
    return path
