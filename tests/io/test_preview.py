import numpy as np
import pytest
from matplotlib.image import imread

from mi_lidar.io import birds_eye_png, range_image_png


@pytest.mark.parametrize("shape", [(16, 1800), (32, 1024), (1, 180), (180, 1)])
def test_range_image_png(tmp_path, shape):
    rng = np.random.default_rng(3)
    ranges = rng.uniform(1, 50, shape).astype(np.float32)
    ranges[rng.random(shape) < 0.2] = np.nan
    path = range_image_png(tmp_path / "r.png", ranges, title="test")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = imread(path)
    height, width = image.shape[:2]
    assert 1000 <= width <= 1600
    assert 250 <= height <= 1200
    assert height / width < 0.6
    magenta = (image[..., 0] > 0.95) & (image[..., 1] < 0.05) & (image[..., 2] > 0.95)
    assert magenta.sum() > 100
    assert [p.name for p in tmp_path.iterdir()] == ["r.png"]


def test_range_image_uses_hit_mask(tmp_path):
    ranges = np.full((16, 200), 10.0)
    hit = np.ones_like(ranges, bool)
    path_all = range_image_png(tmp_path / "a.png", ranges)
    hit[:, :100] = False
    path_half = range_image_png(tmp_path / "b.png", ranges, hit=hit)
    magenta = lambda im: ((im[..., 0] > 0.95) & (im[..., 1] < 0.05) & (im[..., 2] > 0.95)).sum()
    assert magenta(imread(path_half)) > magenta(imread(path_all)) + 10000


def test_birds_eye_png(tmp_path):
    rng = np.random.default_rng(4)
    points = rng.uniform(-20, 20, (5000, 3))
    points[:10] = np.nan
    path = birds_eye_png(tmp_path / "b.png", points, title="bev")
    image = imread(path)
    assert image.shape[0] >= 500 and image.shape[1] >= 500
    assert image[..., :3].std() > 0.05
    path2 = birds_eye_png(tmp_path / "c.png", points, values=np.arange(5000.0), value_label="index")
    assert path2.stat().st_size > 10000
    with pytest.raises(ValueError, match="values"):
        birds_eye_png(tmp_path / "d.png", points, values=np.arange(3.0))


def test_birds_eye_png_of_a_planar_scan_has_no_height_scale(tmp_path):
    """A planar log's points all lie at one height: fit-scene's intel/scene_top.png had a colour bar from -0.1 to
    0.1 m and every point in its middle colour. Now one colour and no colour bar (its ends appear nowhere)."""
    from matplotlib import colormaps

    rng = np.random.default_rng(6)
    points = np.c_[rng.uniform(-20, 20, (4000, 2)), np.zeros(4000)]
    image = imread(birds_eye_png(tmp_path / "flat.png", points, title="planar"))
    blue = np.asarray(colormaps["tab10"](0)[:3])
    assert (np.abs(image[..., :3] - blue).max(axis=-1) < 0.05).sum() > 500
    ends = [np.asarray(colormaps["viridis"](end)[:3]) for end in (0.0, 1.0)]
    near = lambda image, colour: (np.abs(image[..., :3] - colour).max(axis=-1) < 0.05).sum()  # noqa: E731
    assert [near(image, end) for end in ends] == [0, 0]
    points[:, 2] = rng.uniform(0.0, 3.0, 4000)  # heights that vary keep their scale (measured: 814 and 463 pixels)
    image = imread(birds_eye_png(tmp_path / "terrain.png", points, title="terrain"))
    assert min(near(image, end) for end in ends) > 200


def test_overlay_png_draws_each_return_at_its_pixel_in_its_depth_colour(tmp_path):
    """Returns land on their pixel of the enlarged image (10x for a 96-pixel-wide image), coloured from
    the nearest (turbo's first colour) to the farthest (its last); a nearer return covers a farther one."""
    from matplotlib import colormaps
    from PIL import Image

    from mi_lidar.io.preview import overlay_png

    image = np.full((40, 96, 3), 0.2, np.float32)
    uv = np.array([[10.5, 10.5], [10.5, 10.5], [80.2, 30.7], [50.0, 20.0]])
    depth = np.array([5.0, 9.0, 13.0, 9.0])
    page = np.asarray(Image.open(overlay_png(tmp_path / "o.png", image, uv, depth, title="t")).convert("RGB"))
    turbo = (colormaps["turbo"](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)
    top, scale = 24, 10  # title strip above the image; 960 / 96
    assert page.shape[1] > 96 * scale and page.shape[0] == 40 * scale + top
    pixel = lambda u, v: page[int(v * scale) + top, int(u * scale)]  # noqa: E731
    np.testing.assert_array_equal(pixel(10.5, 10.5), turbo[0])  # the nearer of the two at one pixel
    np.testing.assert_array_equal(pixel(80.2, 30.7), turbo[255])
    np.testing.assert_array_equal(pixel(50.0, 20.0), turbo[128])
    grey = np.round(255 * (1.055 * 0.2 ** (1 / 2.4) - 0.055))
    np.testing.assert_array_equal(pixel(30.0, 35.0), [grey] * 3)  # no return there: the sRGB image


def test_birds_eye_png_draws_classes_in_their_own_colours(tmp_path):
    """Labels are classes: each gets a colour of the qualitative palette (tab10: blue, orange, green ...), named
    in a legend, not a shade of one colour scale."""
    from matplotlib import colormaps

    rng = np.random.default_rng(5)
    points = rng.uniform(-20, 20, (6000, 3))
    labels = np.where(points[:, 0] < 0, 1, 7).astype(np.uint32)
    image = imread(birds_eye_png(tmp_path / "l.png", points, values=labels, value_label="label", categorical=True))
    for k in (0, 1):  # the first two palette colours, one per class present
        colour = np.asarray(colormaps["tab10"](k)[:3])
        assert (np.abs(image[..., :3] - colour).max(axis=-1) < 0.05).sum() > 500
    viridis = np.asarray(colormaps["viridis"](1.0)[:3])  # no colour scale: its top colour appears nowhere
    assert (np.abs(image[..., :3] - viridis).max(axis=-1) < 0.05).sum() == 0
