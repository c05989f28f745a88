// Labelled tiles under a title, as one picture (the photometric maps' and textures' contact sheets, the asset's
// driven frame), and the maps' 8-bit previews. Internal to processing: it takes OpenCV's images.
#pragma once

#include <opencv2/core.hpp>
#include <string>
#include <utility>
#include <vector>

namespace stage::processing {

struct Image;

// 8-bit previews (BGR) of the maps: albedo (linear RGB) in sRGB; a unit normal as (n + 1) / 2, `empty` where the
// normal is zero (no surface).
cv::Mat AlbedoPreview(const Image& albedo);
cv::Mat NormalPreview(const Image& normal, const cv::Vec3b& empty = {0, 0, 0});

// Tiles (8-bit BGR, all of the first's size) of at least 256 pixels across (nearest-neighbour enlargement of small
// images), `columns` a row, each under its label, under `title`.
cv::Mat ContactSheet(const std::vector<std::pair<std::string, cv::Mat>>& tiles, const std::string& title,
                     int columns = 3);

}  // namespace stage::processing
