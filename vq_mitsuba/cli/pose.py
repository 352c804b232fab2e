"""`vq-mitsuba pose`: structure from motion into a COLMAP capture (`vq_mitsuba.geometry.poses.pose_capture`)."""

from __future__ import annotations

from vq_mitsuba.cli.common import command_config, help_config, output_option, refuse_file_output
from vq_mitsuba.errors import InputError


def add_parser(sub, shared) -> None:
    p = sub.add_parser(
        "pose", parents=[shared["threads"], output_option("the posed capture to write", metavar="OUT"),
                         shared["config"], shared["quiet"]],
        help="find the camera poses of photos or a video (SfM): a COLMAP capture to fit",
        description="Structure from motion with COLMAP (pycolmap): SIFT features, matching, incremental mapping "
                    "with one camera for all images. SOURCE is a folder of photos (JPEG / PNG, one size; EXIF "
                    "orientation applied) or a video (.mp4 .mov .avi .mkv .webm: the sharpest frame of each of "
                    "pose.frames equal time windows). Writes OUT as a COLMAP capture (the images and the model that "
                    "places the most of them) and OUT/pose.json (images placed, mean reprojection error, timings); refused "
                    "when fewer than pose.min_registered of the images (and at least 3) are placed. Run again on "
                    "the same inputs, OUT is reused. `fit` does this on its own for photos or a video (RUN_DIR/pose/).")
    p.add_argument("source", nargs="?", help="a folder of photos or a video file")
    p.set_defaults(func=run, resume=False)


def run(args) -> int:
    from vq_mitsuba.geometry.poses import pose_capture
    from vq_mitsuba.run.run_dir import check_writable

    if args.help_config:
        return help_config()
    if args.source is None:
        raise InputError(None, "pose needs a folder of photos or a video")
    if args.output is None:
        raise InputError(None, "pose writes a COLMAP capture: give it a folder with -o OUT")
    refuse_file_output(args.output)
    check_writable(args.output)
    cfg = command_config(args)
    summary = pose_capture(args.source, args.output, cfg.pose)
    print(f"{summary['registered']} of {summary['images']} images posed, mean reprojection error "
          f"{summary['mean_reprojection_error_px']:.2f} px: {args.output}/ (a COLMAP capture and pose.json); "
          f"fit it with: vq-mitsuba fit {args.output}")
    return 0
