# OpenCV 4 removed the C API's constant names that VINS-Fusion (and its camera_models) still use.
# Each becomes its C++ name, same value; applied by scripts/build_vins_fusion.sh with `sed -E`.
# Idempotent: on an already changed file nothing matches.
s/\bCV_LOAD_IMAGE_GRAYSCALE\b/cv::IMREAD_GRAYSCALE/g
s/\bCV_AA\b/cv::LINE_AA/g
s/\bCV_BGR2GRAY\b/cv::COLOR_BGR2GRAY/g
s/\bCV_GRAY2BGR\b/cv::COLOR_GRAY2BGR/g
s/\bCV_GRAY2RGB\b/cv::COLOR_GRAY2RGB/g
s/\bCV_CALIB_CB_ADAPTIVE_THRESH\b/cv::CALIB_CB_ADAPTIVE_THRESH/g
s/\bCV_CALIB_CB_NORMALIZE_IMAGE\b/cv::CALIB_CB_NORMALIZE_IMAGE/g
s/\bCV_CALIB_CB_FILTER_QUADS\b/cv::CALIB_CB_FILTER_QUADS/g
s/\bCV_CALIB_CB_FAST_CHECK\b/cv::CALIB_CB_FAST_CHECK/g
s/\bCV_ADAPTIVE_THRESH_MEAN_C\b/cv::ADAPTIVE_THRESH_MEAN_C/g
s/\bCV_THRESH_BINARY_INV\b/cv::THRESH_BINARY_INV/g
s/\bCV_THRESH_BINARY\b/cv::THRESH_BINARY/g
s/\bCV_RETR_CCOMP\b/cv::RETR_CCOMP/g
s/\bCV_CHAIN_APPROX_SIMPLE\b/cv::CHAIN_APPROX_SIMPLE/g
s/\bCV_SHAPE_CROSS\b/cv::MORPH_CROSS/g
s/\bCV_SHAPE_RECT\b/cv::MORPH_RECT/g
s/\bCV_TERMCRIT_EPS\b/cv::TermCriteria::EPS/g
s/\bCV_TERMCRIT_ITER\b/cv::TermCriteria::MAX_ITER/g
