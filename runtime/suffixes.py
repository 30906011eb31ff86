"""The image file suffixes every reader and writer of the project goes by, one list each and
defined only here (no imports, so the command line can check a name without loading numpy):
:data:`IMAGE_SUFFIXES` the image files that can be read and written (renders, batch stills),
:data:`ALPHA_SUFFIXES` those of them that carry an alpha channel, :data:`STILL_SUFFIXES` the 8-bit
stills that cv2 can write as well (PNG, JPEG), plus the two narrower or case-sensitive lists
that the D-NeRF readers match a frame's ``file_path`` against."""

#: Image files that can be read and written (OpenImageIO picks the format from the suffix).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".tif", ".tiff")
#: Those with an alpha channel (JPEG has none).
ALPHA_SUFFIXES = (".png", ".exr", ".tif", ".tiff")
#: 8-bit stills that cv2 can write too: PNG and JPEG. Also, in this order, the suffixes tried
#: for a D-NeRF ``file_path`` without an image extension, and the frame files of a DyNeRF
#: ``camXX/images`` folder.
STILL_SUFFIXES = (".png", ".jpg", ".jpeg")
#: The suffixes (lower-cased) that make a D-NeRF ``file_path`` an image file as it is, for the
#: training reader (nehad.data.dnerf): the stills and EXR, not TIFF.
DNERF_IMAGE_SUFFIXES = STILL_SUFFIXES + (".exr",)
#: The same for the camera reader (runtime.cameras), matched case-sensitively: every image
#: suffix and the stills' upper-case forms.
CAMERA_IMAGE_SUFFIXES = IMAGE_SUFFIXES + tuple(s.upper() for s in STILL_SUFFIXES)

#: Videos that `nehad prepare` decodes (PyAV reads each of them; matched lower-cased).
CAPTURE_VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".mkv", ".avi", ".webm")

__all__ = ["ALPHA_SUFFIXES", "CAMERA_IMAGE_SUFFIXES", "CAPTURE_VIDEO_SUFFIXES",
           "DNERF_IMAGE_SUFFIXES", "IMAGE_SUFFIXES", "STILL_SUFFIXES"]
