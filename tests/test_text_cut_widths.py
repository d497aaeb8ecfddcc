"""Where a word too long for a banner line is cut, on letters whose widths are worked by hand.

Ground truth: OpenCV's Hershey simplex font at scale 1, thickness 1 advances 6 px for "i" and
23 px for "W", and a line of n letters measures 1 px more than its advances (checked below, so
a change of font metrics says so rather than failing the cuts). A cut piece is the longest
prefix that fits the line, never under 8 characters even where 8 are wider than the line.
"""

from __future__ import annotations

import cv2

from appliance.display.text import FONT, wrap_text

I_PX, W_PX = 6, 23


def hand_width(text: str) -> int:
    return 1 + sum(I_PX if ch == "i" else W_PX for ch in text)


def test_the_font_metrics_the_cuts_below_are_worked_from():
    for text in ("i", "W", "i" * 20 + "W" * 20, "W" * 8 + "i" * 40):
        assert cv2.getTextSize(text, FONT, 1.0, 1)[0][0] == hand_width(text), text


def test_a_cut_piece_exactly_as_wide_as_the_line_is_kept_whole():
    # 20 i's are 1 + 120 = 121 px: exactly the line. Narrow letters first, so the average-width
    # estimate (40 * 121 // 581 = 8) falls short and the cut must grow to all 20 of them.
    word = "i" * 20 + "W" * 20
    # The W's: 8 are 185 px, wider than the line, so each piece is the shortest cut, 8 letters.
    assert wrap_text(word, 121, 1.0, 1) == ["i" * 20, "W" * 8, "W" * 8, "W" * 4]


def test_a_piece_shrinks_to_eight_letters_and_no_further_when_eight_are_too_wide():
    # The line is 5 W's wide (116 px). Wide letters first, so the estimate (48 * 116 // 425 = 13)
    # overshoots and the cut shrinks, step by step, to 8 W's (185 px: the shortest cut) and stops.
    word = "W" * 8 + "i" * 40
    # Then 19 i's fit (1 + 114 = 115 px; 20 are 121), twice, and 2 are left.
    assert wrap_text(word, 116, 1.0, 1) == ["W" * 8, "i" * 19, "i" * 19, "i" * 2]
