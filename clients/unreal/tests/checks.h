// What the C++ core's test programs share: a counted check that throws when it fails, and a file's bytes.
#pragma once

#include <fstream>
#include <iterator>
#include <stdexcept>
#include <string>

inline int checks = 0;  // checks passed so far; the programs print it

inline void check(bool ok, const std::string& what) {
    ++checks;
    if (!ok) throw std::runtime_error("check failed: " + what);
}

inline std::string read_file(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    if (!in) throw std::runtime_error("cannot read " + path);
    return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}
