#version 330 core
// Depth pass from the key light: only depth is written.

void main() {
}
