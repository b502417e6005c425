"""Picture sheets (warptex.sheets): 8-bit colours and the slices a row is labelled with."""

import numpy as np

from warptex.sheets import sheet, to_rgb8, volume_row


def test_to_rgb8_rounds_clips_and_spreads_gray():
    values = np.array([0.0, 0.5, 1.0, 1.7, -0.3, 0.2, 0.998], np.float32)
    expected = np.array([0, 128, 255, 255, 0, 51, 254], np.uint8)
    rgb = to_rgb8(np.tile(values[:, None, None], (1, 1, 3)))
    np.testing.assert_array_equal(rgb[:, 0], np.tile(expected[:, None], (1, 3)))
    gray_alpha = np.stack([values, np.full_like(values, 0.1)], -1)[:, None, :]
    np.testing.assert_array_equal(to_rgb8(gray_alpha)[:, 0], np.tile(expected[:, None], (1, 3)))
    assert to_rgb8(np.zeros((2, 3, 5))).shape == (2, 3, 3)


def test_volume_row_slices_each_axis_at_its_label():
    vol = np.zeros((4, 6, 8, 3), np.float32)
    vol[..., 0] = np.arange(4)[:, None, None]
    vol[..., 1] = np.arange(6)[None, :, None]
    vol[..., 2] = np.arange(8)[None, None, :]
    row = volume_row(vol)
    assert [label for label, _ in row] == ["x = 2", "y = 3", "z = 4"]
    for axis, (_, image) in enumerate(row):
        assert np.all(image[..., axis] == vol.shape[axis] // 2)  # the slice it names
        assert sorted(image.shape[:2]) == sorted(s for a, s in enumerate(vol.shape[:3])
                                                 if a != axis)
    assert volume_row(vol, depth=1)[2][0] == "z = 1"


def test_sheet_fits_each_image_in_its_cell_and_enlarges_it_sharply():
    """A 4-row, 8-column checker in a 32-pixel cell: 4x larger, 32 wide and 16 high, each
    pixel a sharp 4x4 block, the rest of the cell white."""
    image = np.zeros((4, 8, 3), np.float32)
    image[(np.arange(4)[:, None] + np.arange(8)[None, :]) % 2 == 1] = 1.0
    out = sheet([("r", [("a", image)])], cell=32)
    x, y = 8 * 1 + 4, 4 + 14  # after the row label; below the image label
    expected = np.kron((image * 255).astype(np.uint8), np.ones((4, 4, 1), np.uint8))
    np.testing.assert_array_equal(out[y:y + 16, x:x + 32], expected)
    assert (out[y + 16:y + 32, x:x + 32] == 255).all()
    assert out.shape == (4 + 14 + 32 + 4, x + 32 + 2 * 4, 3)


def test_a_titled_sheet_holds_its_title_above_the_rows():
    """A sheet passed around without its table names what it shows."""
    image = np.zeros((4, 8, 3), np.float32)
    plain = sheet([("r", [("a", image)])], cell=32)
    titled = sheet([("r", [("a", image)])], cell=32, title="granite_64.png: 64^3, seed 0")
    band = 14 + 4
    np.testing.assert_array_equal(titled[band:, :plain.shape[1]], plain)
    assert (titled[:band] < 128).any()  # the title's text
    assert titled.shape[1] >= 7 * len("granite_64.png: 64^3, seed 0")  # room for it


def test_rows_of_several_images_sit_in_a_grid_with_their_labels():
    """A row of one image and one of three: each image at its column and row, a gap apart,
    each label above its image and each row's name left of it, drawn dark; the sheet as
    wide as the widest row."""
    colors = [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.0, 1.0, 0.0)]
    solid = [np.broadcast_to(np.float32(c), (8, 8, 3)) for c in colors]
    cell, gap, label = 16, 4, 14
    out = sheet([("ex", [("a", solid[0])]), ("method", [("b", solid[1]), ("c", solid[2]),
                                                         ("d", solid[3])])], cell=cell)
    left = 8 * len("method") + gap
    assert out.shape[1] == left + 3 * (cell + gap) + gap
    places = [(0, 0, colors[0])] + [(1, c, colors[c + 1]) for c in range(3)]
    for row, column, color in places:
        x = left + column * (cell + gap)
        y = gap + row * (cell + label + gap)
        np.testing.assert_array_equal(out[y + label:y + label + cell, x:x + cell],
                                      np.broadcast_to(np.uint8(color) * 255, (cell, cell, 3)))
        assert (out[y:y + label, x:x + cell] < 128).any()  # its label
        assert (out[y + label:y + label + cell, :left] < 128).any()  # its row's name
        assert (out[y + label:y + label + cell, x + cell:x + cell + gap] == 255).all()


def test_an_image_shrunk_into_its_cell_is_smoothed():
    """A one-pixel checker shrunk fourfold is grey, not a pick of its black or white."""
    checker = np.zeros((64, 64, 3), np.float32)
    checker[(np.arange(64)[:, None] + np.arange(64)[None, :]) % 2 == 1] = 1.0
    out = sheet([("r", [("a", checker)])], cell=16)
    x, y = 8 + 4, 4 + 14
    assert (np.abs(out[y + 4:y + 12, x + 4:x + 12].astype(int) - 128) < 40).all()
