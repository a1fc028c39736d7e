#!/usr/bin/env python3
"""Draw docs/frames.png: base_link and camera_optical on a robot, seen from its left side
and from above, with the [frames.base_from_camera] example of systemd/cubeloc.toml
(xyz = [0.30, 0.00, 1.10], rpy_deg = [-90, 0, -90]). Run from the repository root."""

from pathlib import Path

import cv2
import numpy as np

RED, GREEN, BLUE, GREY, BLACK = (40, 40, 220), (40, 160, 40), (200, 90, 30), (170, 170, 170), (30, 30, 30)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def arrow(img, start, direction, colour, label):
    end = (int(start[0] + 90 * direction[0]), int(start[1] + 90 * direction[1]))
    cv2.arrowedLine(img, start, end, colour, 3, cv2.LINE_AA, tipLength=0.18)
    cv2.putText(img, label, (end[0] + 6 * np.sign(direction[0]) - (18 if direction[0] < 0 else 0),
                             end[1] + (18 if direction[1] > 0 else -6)), FONT, 0.6, colour, 2, cv2.LINE_AA)


def out_of_page(img, centre, colour, label, into=False):
    cv2.circle(img, centre, 9, colour, 2, cv2.LINE_AA)
    if into:  # a cross: pointing away from the viewer
        for s in (-1, 1):
            cv2.line(img, (centre[0] - 6, centre[1] - 6 * s), (centre[0] + 6, centre[1] + 6 * s), colour, 2, cv2.LINE_AA)
    else:  # a dot: pointing at the viewer
        cv2.circle(img, centre, 3, colour, -1, cv2.LINE_AA)
    cv2.putText(img, label, (centre[0] + 12, centre[1] + 20), FONT, 0.6, colour, 2, cv2.LINE_AA)


def main() -> None:
    img = np.full((460, 980, 3), 255, np.uint8)
    scale, floor, left = 250, 400, 150  # pixels per metre; side view origin (base_link) at (left, floor)
    cv2.putText(img, "side view (from the robot's left)", (20, 30), FONT, 0.7, BLACK, 2, cv2.LINE_AA)
    cv2.line(img, (20, floor), (470, floor), GREY, 2)
    cv2.rectangle(img, (left - 110, floor - 110), (left + 110, floor - 30), GREY, 2)  # body
    for x in (left - 70, left + 70):
        cv2.circle(img, (x, floor - 28), 26, GREY, 2)  # wheels
    camera = (left + int(0.30 * scale), floor - int(1.10 * scale))
    cv2.line(img, (left + int(0.30 * scale), floor - 110), camera, GREY, 2)  # mast
    cv2.rectangle(img, (camera[0] - 18, camera[1] - 14), (camera[0] + 18, camera[1] + 14), GREY, 2)
    base = (left, floor - 4)
    arrow(img, base, (1, 0), RED, "x (ahead)")
    arrow(img, base, (0, -1), BLUE, "z (up)")
    out_of_page(img, base, GREEN, "y (left)")
    cv2.putText(img, "base_link", (base[0] - 130, base[1] - 60), FONT, 0.6, BLACK, 1, cv2.LINE_AA)
    arrow(img, camera, (1, 0), BLUE, "z (optical axis)")
    arrow(img, camera, (0, 1), GREEN, "y (down)")
    out_of_page(img, camera, RED, "x (right)", into=True)
    cv2.putText(img, "camera_optical", (camera[0] - 150, camera[1] - 24), FONT, 0.6, BLACK, 1, cv2.LINE_AA)
    cv2.putText(img, "xyz = [0.30, 0.00, 1.10]: the camera's centre from base_link", (20, 440), FONT, 0.5, BLACK, 1,
                cv2.LINE_AA)

    ox, oy = 720, 300  # top view, base_link at (ox, oy), x ahead = to the right, y left = up the page
    cv2.putText(img, "top view", (520, 30), FONT, 0.7, BLACK, 2, cv2.LINE_AA)
    cv2.rectangle(img, (ox - 110, oy - 80), (ox + 110, oy + 80), GREY, 2)
    arrow(img, (ox, oy), (1, 0), RED, "x")
    arrow(img, (ox, oy), (0, -1), GREEN, "y")
    out_of_page(img, (ox, oy), BLUE, "z")
    cam = (ox + int(0.30 * scale), oy - 160)
    cv2.line(img, (cam[0], oy), (cam[0], cam[1] + 16), GREY, 1, cv2.LINE_AA)
    cv2.putText(img, "(camera drawn off the body to keep it legible)", (520, 440), FONT, 0.45, BLACK, 1, cv2.LINE_AA)
    arrow(img, cam, (1, 0), BLUE, "z")
    arrow(img, cam, (0, 1), RED, "x (right)")
    out_of_page(img, cam, GREEN, "y (down)", into=True)
    cv2.putText(img, "rpy_deg = [-90, 0, -90]", (520, 410), FONT, 0.5, BLACK, 1, cv2.LINE_AA)
    out = Path("docs/frames.png")
    cv2.imwrite(str(out), img)
    print(out)


if __name__ == "__main__":
    main()
