"""Camera frames: ROS 2 images in CDR, JPEG at a rung, their quality, a camera over photographs.

What quality as a second knob needs besides the allocation: ``images`` (``sensor_msgs/msg/Image``
and ``CompressedImage`` in CDR, through rosbags: no ROS 2 needed), ``jpeg`` (libjpeg-turbo
through simplejpeg, at a resolution scale and a JPEG quality), ``ssim`` (the quality score),
``ladder`` (a camera's ladder measured on its own frames) and ``photos`` (a camera moving over
real photographs, for the paper's experiment). The ``quality`` extra brings what they need.
"""

__all__: list[str] = []
