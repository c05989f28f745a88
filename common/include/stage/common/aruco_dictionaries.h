// OpenCV's predefined ArUco dictionaries by name, in the order of cv::aruco::PREDEFINED_DICTIONARY_NAME: the index of
// a name is its OpenCV id. Shared by the simulator's board and calibration, without OpenCV's headers.
#pragma once

#include <string>

namespace stage {

inline constexpr const char* kArucoDictionaries[] = {
    "DICT_4X4_50",  "DICT_4X4_100",  "DICT_4X4_250",  "DICT_4X4_1000", "DICT_5X5_50",  "DICT_5X5_100",
    "DICT_5X5_250", "DICT_5X5_1000", "DICT_6X6_50",   "DICT_6X6_100",  "DICT_6X6_250", "DICT_6X6_1000",
    "DICT_7X7_50",  "DICT_7X7_100",  "DICT_7X7_250",  "DICT_7X7_1000", "DICT_ARUCO_ORIGINAL"};

// OpenCV's id of dictionary `name`, or -1.
inline int ArucoDictionaryId(const std::string& name) {
  for (int i = 0; i < static_cast<int>(sizeof(kArucoDictionaries) / sizeof(kArucoDictionaries[0])); ++i) {
    if (name == kArucoDictionaries[i]) return i;
  }
  return -1;
}

// The names, comma-separated, for error messages.
inline std::string ArucoDictionaryNames() {
  std::string names;
  for (const char* n : kArucoDictionaries) names += (names.empty() ? "" : ", ") + std::string(n);
  return names;
}

}  // namespace stage
