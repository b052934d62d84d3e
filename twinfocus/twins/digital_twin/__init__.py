"""Digital twin of the reference: from what the tracking stereo camera sees to a simulated SAR
amplitude template (source paper, section 4.3).

Stages, one module each: ``camera`` (calibrated stereo pair, rectification, camera-to-scene
pose), ``render`` (synthetic stereo views of a simulated scene, with truth), ``stereo`` (SGBM
disparity with WLS filtering, depth), ``segment`` (classical reference segmentation and the
SAM-family plug-in), ``pointcloud`` (masked depth -> cleaned, down-sampled cloud in the scene
frame), ``template`` (simulated amplitude template), ``align`` (radar-camera offset calibration
and per-scan registration) and ``pipeline`` (the stages chained, with timings).
"""
